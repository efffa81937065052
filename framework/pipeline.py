"""Run a validated spec end to end and write the output folder.

Outputs (the contract other tools read, see ``docs/outputs.md``):

- ``homographies.npy``: (T, 3, 3) float64, frame pixel coordinates to panorama pixel
  coordinates (x right, y down, pixel centres at integers), one per binary frame.
- ``panorama.npy``: (H, W) float32 linear flux in photons/s, NaN where unobserved.
- ``panorama.tif``: the same flux as a float32 TIFF, its second page the validity mask.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel

from . import __version__
from .errors import PhotonpanoError
from .hdr import write_flux_tiff
from .host import PluginHost
from .outputs import json_default
from .progress import reporting, start_task
from .spec import dump_spec

__all__ = ["RunResult", "prepare_output", "run_pipeline", "reconstruct", "ground_truth_report", "library_versions"]


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


@dataclass(frozen=True)
class RunResult:
    """What a run produced (the Python API returns it; ``run.json`` holds ``summary``).

    Attributes:
        spec: the validated ``PipelineSpec``.
        homographies: (T, 3, 3) float64 frame-to-canvas homographies, one per binary
            frame: frame pixel coordinates (x right, y down, pixel centres at integers)
            to panorama canvas pixels (including the super-resolution scale).
        panorama: (Hc, Wc) float32 linear flux of the panorama canvas in photons/s, NaN
            where no frame looked (``panorama.npy``).
        summary: the ``run.json`` content (versions, spec, timings, per-level
            statistics, ground truth report if known).
        out_dir: the output folder, or None for a run kept in memory.
    """

    spec: BaseModel
    homographies: NDArray[np.float64]
    panorama: NDArray[np.float32]
    summary: dict[str, Any]
    out_dir: Path | None = None


def run_pipeline(spec: BaseModel, out_dir: Path | None, host: PluginHost, *, force: bool = False,
                 resume: bool = False) -> RunResult:
    """Run ``spec`` and, if ``out_dir`` is given, write every output into it.

    Outputs are written atomically, ``run.json`` last, under a lock and a manifest
    (:class:`~photonpano.outputs.RunFolder`, ``docs/outputs.md``); nothing is written
    before the source is open, and a failed run removes what it wrote.

    Args:
        spec: a validated ``PipelineSpec`` (see :func:`photonpano.spec.load_spec`).
        out_dir: output folder (created; must be empty unless ``force`` or ``resume``),
            or None to keep the results in memory only (nothing is written; observers
            get ``out_dir=None``).
        host: the plugin host (its lifecycle hooks are called).
        force: replace the previous run's outputs in ``out_dir`` (the files its
            manifest lists; nothing else is touched).
        resume: continue the interrupted run in ``out_dir`` from its last finished
            level (same spec); the homographies equal those of an uninterrupted run.

    Returns:
        The :class:`RunResult`.

    Raises:
        PhotonpanoError: bad output folder, unreadable source, failed stage.
    """
    from .outputs import RunFolder
    from .spec import check_available

    check_available(spec)
    with reporting(host):
        if out_dir is None:
            return _run_into(spec, None, host)
        with RunFolder(out_dir, force=force, resume=resume, inputs=_input_paths(spec)) as folder:
            return _run_into(spec, folder, host)


def _input_paths(spec: BaseModel) -> list[Path]:
    """The existing files and folders named by the spec's source section."""
    return [value for value in vars(spec.source).values() if isinstance(value, Path) and value.exists()]


def _resume_state(folder, spec_text: str):
    """Return the checkpoint to continue from (None: start at level 1); the spec must not change."""
    from .outputs import OutputError

    previous = folder.root / "spec.yaml"
    if previous.is_file() and previous.read_text() != spec_text:
        raise OutputError(f"--resume: the spec differs from that of the interrupted run in {previous}; "
                          "resume with the same spec, or pass --force to start anew")
    return folder.last_checkpoint()


def _run_into(spec: BaseModel, folder, host: PluginHost) -> RunResult:
    """Run ``spec``, writing into ``folder`` (a :class:`~photonpano.outputs.RunFolder`) unless it is None."""
    from .photons import tone_map

    out_dir = folder.root if folder is not None else None
    progress = start_task
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    source = spec.source.build()
    timings["source"] = time.perf_counter() - t0
    spec_text = dump_spec(spec)
    start = _resume_state(folder, spec_text) if folder is not None and folder.resume else None
    if folder is not None:
        folder.write_text("spec.yaml", spec_text)
    host.hook.photonpano_run_start(spec=spec, source=source, out_dir=out_dir)

    def on_level(result):
        host.hook.photonpano_level_finished(level=result, spec=spec, source=source, out_dir=out_dir)
        if folder is not None:
            folder.adopt_new_files()  # what observers wrote

    confidence: dict[str, Any] = {}
    homographies, stats, pano, stage_timings = reconstruct(
        spec, source, on_level=on_level, progress=progress, resume=start, report=confidence,
        checkpoint=folder.save_checkpoint if folder is not None else None)
    timings.update(stage_timings)

    if folder is not None:
        folder.save_npy("homographies.npy", pano.homographies)
        folder.save_npy("panorama.npy", pano.flux)
        folder.write_with("panorama.tif", lambda path: write_flux_tiff(path, pano.flux))
        if spec.outputs.panorama_png:
            folder.write_with("panorama.png", lambda path: _write_png(path, tone_map(pano.flux, bits=16)))
    host.hook.photonpano_panorama_finished(panorama=pano, spec=spec, source=source, out_dir=out_dir)
    if folder is not None:
        folder.adopt_new_files()  # what observers wrote

    summary: dict[str, Any] = {
        **run_header(spec, host, source),
        **confidence,
        "panorama": {"height": int(pano.flux.shape[0]), "width": int(pano.flux.shape[1]),
                     "observed_fraction": float(np.isfinite(pano.flux).mean())},
        "levels": stats,
        "timings_s": timings,
    }
    if start is not None:
        summary["resumed_after_level"] = start.level
    error = None
    if source.ground_truth is not None:
        t0 = time.perf_counter()
        advance = progress("ground truth report", source.n_frames) if source.scene_flux is not None else None
        summary["ground_truth"] = ground_truth_report(source, homographies, pano, spec.panorama_subbatch_px,
                                                      compositor=spec.compositor, progress=advance)
        timings["ground_truth_report"] = time.perf_counter() - t0
        error = _trajectory_error(homographies, source)
    if folder is not None and spec.outputs.trajectory_plot:
        folder.write_with("trajectory.png",
                          lambda path: _plot_trajectory(path, homographies, pano.homographies, source, error))
    host.hook.photonpano_run_finished(spec=spec, summary=summary, out_dir=out_dir)
    if folder is not None:
        folder.commit(json.dumps(summary, indent=2, default=json_default))
    return RunResult(spec=spec, homographies=pano.homographies, panorama=pano.flux, summary=summary, out_dir=out_dir)


#: distributions whose versions every run.json records (import name -> distribution).
CORE_LIBRARIES = {"numpy": "numpy", "cv2": "opencv-python-headless", "numba": "numba", "scipy": "scipy",
                  "pluggy": "pluggy", "pydantic": "pydantic"}


def run_header(spec: BaseModel, host: PluginHost, source: Any) -> dict[str, Any]:
    """Return the first keys of every ``run.json``: versions, the resolved spec, the capture.

    Returns:
        ``{"photonpano", "python", "versions", "plugins", "spec", "source"}`` (see
        :func:`library_versions` and ``PhotonSource.describe``).
    """
    return {"photonpano": __version__, "python": platform.python_version(), "versions": library_versions(spec),
            "plugins": host.versions(), "spec": spec.model_dump(mode="json"), "source": source.describe()}


def library_versions(spec: BaseModel | None = None) -> dict[str, str]:
    """Return the versions of the core libraries and of the optional backends ``spec`` uses.

    Args:
        spec: a validated ``PipelineSpec``; the ``requires`` of its stages' configs (e.g.
            torch and kornia for ``kornia-sift``) are added. None: core libraries only.

    Returns:
        ``{import name: version}``; ``"not installed"`` for a missing one. OpenCV's is
        ``cv2.__version__`` (whatever wheel provides it).
    """
    import importlib
    from importlib import metadata

    from .stages import STAGES

    names = list(CORE_LIBRARIES)
    if spec is not None:
        for slot in (*STAGES, "refine_locator"):
            config = getattr(spec, slot, None)
            names += [name for name in getattr(type(config), "requires", ()) if name not in names]
    versions: dict[str, str] = {}
    for name in names:
        try:
            versions[name] = str(getattr(importlib.import_module(name), "__version__"))
        except (ImportError, AttributeError):
            try:
                versions[name] = metadata.version(CORE_LIBRARIES.get(name, name))
            except metadata.PackageNotFoundError:
                versions[name] = "not installed"
    return versions


def reconstruct(spec: BaseModel, source, *, on_level=None, progress=None, checkpoint=None, resume=None,
                report: dict[str, Any] | None = None):
    """Estimate the motion of ``source`` and assemble its panorama as ``spec`` says.

    Args:
        spec: a validated ``PipelineSpec`` (its ``source`` section is not used).
        source: the opened capture.
        on_level: called with each :class:`~photonpano.reconstruct.LevelResult`.
        progress: ``progress(task, total)`` returning an ``advance(n)`` callable.
        checkpoint: called with a :class:`~photonpano.outputs.Checkpoint` after each level.
        resume: a :class:`~photonpano.outputs.Checkpoint` to continue from (None: level 1).
        report: filled, if given, with the confidence report of ``run.json``:
            ``status``, ``warnings``, ``group_size`` (the plan: chosen m and why, see
            :class:`~photonpano.adaptive.GroupPlan`) and ``panorama_agreement``
            (:func:`~photonpano.quality.panorama_agreement`).

    Returns:
        ``(homographies, level_statistics, panorama, timings_s)``: (T, 3, 3) float64
        frame-to-canvas homographies, one statistics dict per level (with the
        trajectory RMSE when the source has ground truth), the
        :class:`~photonpano.compose.Panorama` (from the spec's compositor) and wall
        times in seconds.
    """
    from .adaptive import plan_group_size
    from .coarse import CascadeLocator
    from .compose import compose
    from .executor import make_executor
    from .outputs import Checkpoint
    from .quality import agreement_binning, assess, level_figures, panorama_agreement
    from .reconstruct import estimate_motion

    stats: list[dict[str, Any]] = list(resume.statistics) if resume is not None else []
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
        if checkpoint is not None:
            t = result.template
            checkpoint(Checkpoint(result.level, result.homographies, list(stats),
                                  None if t is None else (t.flux, t.frames, t.homographies)))

    timings: dict[str, float] = {}
    with make_executor(spec.executor, spec.workers) as executor:
        t0 = time.perf_counter()
        homographies, _ = estimate_motion(
            source, spec.resampler.build(), merger, locator, spec.interpolator.build(),
            levels=spec.levels, group_size=plan.group_size, pair_offsets=tuple(spec.pair_offsets),
            executor=executor, refine_locator=spec.refine_locator.build if spec.refine_locator else None,
            keep_merged=spec.outputs.merged_frames, on_level=level_done, progress=progress,
            **({} if resume is None else _start_state(resume)))
        timings["levels"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        advance = progress("panorama", source.n_frames) if progress else None
        pano = compose(source, homographies, spec.compositor.build(), subbatch_px=spec.panorama_subbatch_px,
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


def _start_state(resume) -> dict[str, Any]:
    from .compose import Panorama

    template = None if resume.template is None else Panorama(*resume.template)
    return {"start_level": resume.level + 1, "initial": resume.homographies, "template": template}


def _trajectory_error(homographies: np.ndarray, source):
    from .metrics import trajectory_error

    return trajectory_error(homographies, source.ground_truth, source.width, source.height)


def _rmse(homographies: np.ndarray, source) -> float:
    return _trajectory_error(homographies, source).rmse_px


def ground_truth_report(source, homographies: np.ndarray, pano, subbatch_px: float, *,
                        compositor: Any = None, references: tuple[Any, ...] = (),
                        progress: Any = None) -> dict[str, Any]:
    """Measure a reconstruction against a capture's ground truth.

    The trajectory error is taken after the best global alignment G (the panorama's
    coordinate frame is arbitrary). For the panorama, the true homographies are carried
    into the estimated canvas through G and a second panorama is composited with them
    *on the same canvas* by the same compositor; both are compared with the true scene
    flux resampled onto that canvas, so the PSNR gap measures only what the estimated
    motion costs.

    Args:
        source: a capture with ``ground_truth`` (and ``scene_flux`` for the PSNR;
            ``scene_pitch`` scene pixels per ground-truth unit, default 1).
        homographies: (T, 3, 3) float64 estimated frame-to-panorama homographies.
        pano: the estimated :class:`~photonpano.compose.Panorama`.
        subbatch_px: sub-batch tolerance used for the reference panorama.
        compositor: the compositor config that made ``pano`` (built afresh for the
            reference); None: the bilinear ``flux-canvas`` merge.
        references: more compositor configs to composite the true motion with on the
            same canvas, scored on the same pixels (e.g. ``flux-canvas`` to measure
            what drizzle gains).
        progress: called with the number of binary frames composited into the true-motion
            reference.

    Returns:
        ``{"trajectory_rmse_px", "trajectory_max_px"}`` and, with a scene, ``"psnr_db",
        "psnr_true_homographies_db", "psnr_gap_db"`` and, with ``references``,
        ``"psnr_true_homographies_by"``: plugin key -> PSNR in dB.
    """
    import cv2

    from .compose import BilinearCompositor, compose
    from .metrics import psnr, scene_on_canvas

    err = _trajectory_error(homographies, source)
    report: dict[str, Any] = {"trajectory_rmse_px": err.rmse_px,
                              "trajectory_max_px": float(err.per_frame_px.max())}
    if source.scene_flux is None:
        return report
    canvas_from_scene = _canvas_from_scene(homographies, pano.homographies, err)
    shape = pano.flux.shape
    truths = [compose(source, canvas_from_scene @ source.ground_truth,
                      config.build() if config is not None else BilinearCompositor(),
                      subbatch_px=subbatch_px, canvas_shape=shape, progress=progress if config is compositor else None)
              for config in (compositor, *references)]
    scene = scene_on_canvas(source, canvas_from_scene, shape)
    both = np.isfinite(pano.flux) & np.isfinite(scene)
    for truth in truths:
        both &= np.isfinite(truth.flux)
    mask = cv2.erode(both.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    estimated_db, true_db = psnr(pano.flux, scene, mask), psnr(truths[0].flux, scene, mask)
    report.update(psnr_db=estimated_db, psnr_true_homographies_db=true_db, psnr_gap_db=true_db - estimated_db)
    if references:
        report["psnr_true_homographies_by"] = {config.plugin: psnr(truth.flux, scene, mask)
                                               for config, truth in zip(references, truths[1:])}
    return report


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), image):
        raise PhotonpanoError(f"cannot write {path}")


def _canvas_from_scene(homographies: np.ndarray, to_canvas: np.ndarray, error) -> np.ndarray:
    """(3, 3) homography from ground-truth scene coordinates to the panorama canvas.

    ``homographies`` map frames to the middle frame's coordinates, ``to_canvas`` the same
    frames to the canvas; ``error.alignment`` maps the former to the scene.
    """
    canvas_from_pano = to_canvas[0] @ np.linalg.inv(homographies[0])
    return canvas_from_pano @ np.linalg.inv(error.alignment)


def _plot_trajectory(path: Path, homographies: np.ndarray, to_canvas: np.ndarray, source, error) -> None:
    """Plot the frame centres over time in canvas pixels, and the per-frame error if known.

    Args:
        path: the PNG to write.
        homographies: (T, 3, 3) frame-to-middle-frame homographies (the estimate's gauge).
        to_canvas: (T, 3, 3) frame-to-canvas homographies (``homographies.npy``).
        source: the capture (frame size, frame rate, ground truth).
        error: the :class:`~photonpano.metrics.TrajectoryError` of the estimate, or None.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from . import geometry

    centre = np.array([[(source.width - 1) / 2, (source.height - 1) / 2]])
    t = np.arange(len(to_canvas)) / source.frame_rate_hz
    panels = 3 if error is not None else 2
    fig, axes = plt.subplots(panels, 1, figsize=(8, 2.2 * panels + 0.6), sharex=True)
    est = geometry.apply(to_canvas, centre)[:, 0]
    truth = None
    if error is not None:
        truth = geometry.apply(_canvas_from_scene(homographies, to_canvas, error) @ source.ground_truth, centre)[:, 0]
    for axis, name in enumerate("xy"):
        if truth is not None:
            axes[axis].plot(t, truth[:, axis], color="0.6", lw=3, label="true")
        axes[axis].plot(t, est[:, axis], color="C0", lw=1, label="estimated")
        axes[axis].set_ylabel(f"centre {name} (canvas px)")
    axes[0].legend(loc="best")
    if error is not None:
        axes[2].plot(t, error.per_frame_px, color="C3", lw=1)
        axes[2].set_ylabel("error (scene px)")
        axes[2].set_title(f"per-frame mean corner error after global alignment (RMSE {error.rmse_px:.3f} px)",
                          fontsize=9)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
