"""Run a validated spec end to end and write the output folder.

Outputs (the contract other tools read, see ``docs/outputs.md``):

- ``homographies.npy``: (T, 3, 3) float64, frame pixel coordinates to panorama pixel
  coordinates (x right, y down, pixel centres at integers), one per binary frame.
- ``panorama.npy``: (H, W) float32 linear flux in photons/s, NaN where unobserved.
- ``panorama.png``: the panorama tone-mapped to 16-bit sRGB.
- ``run.json``: versions, spec, timings per stage and level, per-level statistics and,
  for simulated captures, the accuracy against ground truth.
- ``spec.yaml``: the resolved spec (defaults filled in).
- optional: ``level_<k>/`` merged frames, ``trajectory.png``.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel

from . import __version__
from .errors import PhotonpanoError
from .host import PluginHost
from .spec import dump_spec

__all__ = ["prepare_output", "run_pipeline", "ground_truth_report"]


def prepare_output(out_dir: Path, force: bool) -> None:
    """Create ``out_dir``, refusing to write into a non-empty folder unless ``force``.

    Raises:
        PhotonpanoError: if ``out_dir`` is a file, or a non-empty folder without ``force``.
    """
    if out_dir.exists() and not out_dir.is_dir():
        raise PhotonpanoError(f"output {out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise PhotonpanoError(f"output folder {out_dir} is not empty; choose another or pass --force")
    out_dir.mkdir(parents=True, exist_ok=True)


def _progress(host: PluginHost):
    def start(task: str, total: int | None):
        host.hook.photonpano_progress(task=task, total=total, advance=0)
        return lambda n: host.hook.photonpano_progress(task=task, total=total, advance=n)
    return start


def run_pipeline(spec: BaseModel, out_dir: Path, host: PluginHost, *, force: bool = False) -> dict[str, Any]:
    """Run ``spec`` and write every output into ``out_dir``.

    Args:
        spec: a validated ``PipelineSpec`` (see :func:`photonpano.spec.load_spec`).
        out_dir: output folder (created; must be empty unless ``force``).
        host: the plugin host (its lifecycle hooks are called).
        force: allow writing into a non-empty folder (files of the same name are
            replaced; nothing else is touched).

    Returns:
        The ``run.json`` summary.

    Raises:
        PhotonpanoError: bad output folder, unreadable source, failed stage.
    """
    from .photons import tone_map

    for stage in ("source", "resampler", "merger", "locator", "interpolator"):
        type(getattr(spec, stage)).check_available()
    prepare_output(out_dir, force)
    (out_dir / "spec.yaml").write_text(dump_spec(spec))
    progress = _progress(host)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    source = spec.source.build()
    timings["source"] = time.perf_counter() - t0
    host.hook.photonpano_run_start(spec=spec, source=source, out_dir=out_dir)

    def on_level(result):
        host.hook.photonpano_level_finished(level=result, spec=spec, source=source, out_dir=out_dir)

    confidence: dict[str, Any] = {}
    homographies, stats, pano, stage_timings = reconstruct(spec, source, on_level=on_level, progress=progress,
                                                           report=confidence)
    timings.update(stage_timings)

    np.save(out_dir / "homographies.npy", pano.homographies)
    np.save(out_dir / "panorama.npy", pano.flux)
    if spec.outputs.panorama_png:
        _write_png(out_dir / "panorama.png", tone_map(pano.flux, bits=16))

    summary: dict[str, Any] = {
        "photonpano": __version__,
        "python": platform.python_version(),
        "plugins": host.versions(),
        "spec": spec.model_dump(mode="json"),
        "source": source.describe(),
        **confidence,
        "panorama": {"height": int(pano.flux.shape[0]), "width": int(pano.flux.shape[1]),
                     "observed_fraction": float(np.isfinite(pano.flux).mean())},
        "levels": stats,
        "timings_s": timings,
    }
    if source.ground_truth is not None:
        t0 = time.perf_counter()
        summary["ground_truth"] = ground_truth_report(source, homographies, pano, spec.panorama_subbatch_px)
        timings["ground_truth_report"] = time.perf_counter() - t0
    if spec.outputs.trajectory_plot:
        _plot_trajectory(out_dir / "trajectory.png", homographies, source)
    (out_dir / "run.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    host.hook.photonpano_run_finished(spec=spec, summary=summary, out_dir=out_dir)
    return summary


def reconstruct(spec: BaseModel, source, *, on_level=None, progress=None,
                report: dict[str, Any] | None = None):
    """Estimate the motion of ``source`` and assemble its panorama as ``spec`` says.

    Args:
        spec: a validated ``PipelineSpec`` (its ``source`` section is not used).
        source: the opened capture.
        on_level: called with each :class:`~photonpano.reconstruct.LevelResult`.
        progress: ``progress(task, total)`` returning an ``advance(n)`` callable.
        report: filled, if given, with the confidence report of ``run.json``:
            ``status``, ``warnings``, ``group_size`` (the plan: chosen m and why, see
            :class:`~photonpano.adaptive.GroupPlan`) and ``panorama_agreement``
            (:func:`~photonpano.quality.panorama_agreement`).

    Returns:
        ``(homographies, level_statistics, panorama, timings_s)``: (T, 3, 3) float64
        frame-to-canvas homographies, one statistics dict per level (with the
        trajectory RMSE when the source has ground truth), the
        :class:`~photonpano.reconstruct.Panorama` and wall times in seconds.
    """
    from .adaptive import plan_group_size
    from .coarse import CascadeLocator
    from .executor import make_executor
    from .quality import agreement_binning, assess, level_figures, panorama_agreement
    from .reconstruct import assemble_panorama, estimate_motion

    stats: list[dict[str, Any]] = []
    plan = plan_group_size(spec.group_size, source)
    locator = spec.locator.build()
    if plan.auto:  # explicit group sizes keep the plain locator
        locator = CascadeLocator(locator, plan.binning)
    merger = spec.merger.build()

    def level_done(result):
        if on_level is not None:
            on_level(result)
        row = result.statistics()
        if result.locator_cache is not None:  # levels against the panorama: their own locators
            row["locator_cache"] = result.locator_cache
        elif hasattr(locator, "cache_stats"):  # feature reuse of the built-in locators
            row["locator_cache"] = locator.cache_stats()
            locator.reset_cache_stats()
        row["quality"] = level_figures(result, plan, source.width, source.height)
        if isinstance(locator, CascadeLocator) and result.locator_cache is None:
            row["registration_check"] = locator.take_statistics()
        if source.ground_truth is not None:
            row["trajectory_rmse_px"] = _rmse(result.homographies, source)
        stats.append(row)
        result.merged = None  # free memory; observers have seen it

    timings: dict[str, float] = {}
    with make_executor(spec.executor, spec.workers) as executor:
        t0 = time.perf_counter()
        homographies, _ = estimate_motion(
            source, spec.resampler.build(), merger, locator, spec.interpolator.build(),
            levels=spec.levels, group_size=plan.group_size, pair_offsets=tuple(spec.pair_offsets),
            executor=executor, refine_locator=spec.refine_locator.build if spec.refine_locator else None,
            keep_merged=spec.outputs.merged_frames, on_level=level_done, progress=progress)
        timings["levels"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        advance = progress("panorama", source.n_frames) if progress else None
        pano = assemble_panorama(source, homographies, scale=spec.scale, subbatch_px=spec.panorama_subbatch_px,
                                 progress=advance, executor=executor)
        timings["panorama"] = time.perf_counter() - t0
    if report is not None:
        t0 = time.perf_counter()
        agreement = panorama_agreement(source, merger, homographies, pano, plan.group_size,
                                       agreement_binning(plan))
        status, warnings = assess(plan, stats, agreement)
        report.update(status=status, warnings=warnings, group_size=plan.record(),
                      panorama_agreement=agreement)
        timings["confidence"] = time.perf_counter() - t0
    return homographies, stats, pano, timings


def _rmse(homographies: np.ndarray, source) -> float:
    from .metrics import trajectory_error

    return trajectory_error(homographies, source.ground_truth, source.width, source.height).rmse_px


def ground_truth_report(source, homographies: np.ndarray, pano, subbatch_px: float) -> dict[str, Any]:
    """Measure a reconstruction against a capture's ground truth.

    The trajectory error is taken after the best global alignment G (the panorama's
    coordinate frame is arbitrary). For the panorama, the true homographies are carried
    into the estimated canvas through G and a second panorama is merged with them *on
    the same canvas*; both are compared with the true scene flux resampled onto that
    canvas, so the PSNR gap measures only what the estimated motion costs.

    Args:
        source: a capture with ``ground_truth`` (and ``scene_flux`` for the PSNR).
        homographies: (T, 3, 3) float64 estimated frame-to-panorama homographies.
        pano: the estimated :class:`~photonpano.reconstruct.Panorama`.
        subbatch_px: sub-batch tolerance used for the reference panorama.

    Returns:
        ``{"trajectory_rmse_px", "trajectory_max_px"}`` and, with a scene, ``"psnr_db",
        "psnr_true_homographies_db", "psnr_gap_db"``.
    """
    import cv2

    from .metrics import psnr, trajectory_error
    from .reconstruct import assemble_panorama

    err = trajectory_error(homographies, source.ground_truth, source.width, source.height)
    report: dict[str, Any] = {"trajectory_rmse_px": err.rmse_px,
                              "trajectory_max_px": float(err.per_frame_px.max())}
    if source.scene_flux is None:
        return report
    canvas_from_pano = pano.homographies[0] @ np.linalg.inv(homographies[0])
    canvas_from_scene = canvas_from_pano @ np.linalg.inv(err.alignment)
    shape = pano.flux.shape
    truth = assemble_panorama(source, canvas_from_scene @ source.ground_truth, subbatch_px=subbatch_px,
                              canvas_shape=shape)
    scene = cv2.warpPerspective(source.scene_flux, canvas_from_scene, shape[::-1], flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    both = np.isfinite(pano.flux) & np.isfinite(truth.flux) & np.isfinite(scene)
    mask = cv2.erode(both.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    estimated_db, true_db = psnr(pano.flux, scene, mask), psnr(truth.flux, scene, mask)
    report.update(psnr_db=estimated_db, psnr_true_homographies_db=true_db, psnr_gap_db=true_db - estimated_db)
    return report


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), image):
        raise PhotonpanoError(f"cannot write {path}")


def _plot_trajectory(path: Path, homographies: np.ndarray, source) -> None:
    """Plot the frame centres over time (estimated, and true after alignment if known)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from . import geometry

    centre = np.array([[(source.width - 1) / 2, (source.height - 1) / 2]])
    t = np.arange(len(homographies)) / source.frame_rate_hz
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    est = geometry.apply(homographies, centre)[:, 0]
    truth = None
    if source.ground_truth is not None:
        from .metrics import trajectory_error

        align = trajectory_error(homographies, source.ground_truth, source.width, source.height).alignment
        truth = geometry.apply(np.linalg.inv(align) @ source.ground_truth, centre)[:, 0]
    for axis, name in enumerate("xy"):
        axes[axis].plot(t, est[:, axis], label="estimated", lw=1)
        if truth is not None:
            axes[axis].plot(t, truth[:, axis], "--", label="true", lw=1)
        axes[axis].set_ylabel(f"frame centre {name} (panorama px)")
    axes[0].legend()
    axes[1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
