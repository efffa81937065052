"""Run a validated spec end to end and write the output folder.

Outputs (the contract other tools read, see ``docs/outputs.md``):

- ``homographies.npy``: (T, 3, 3) float64, frame pixel coordinates to panorama pixel
  coordinates (x right, y down, pixel centres at integers), one per binary frame.
- ``panorama.npy``: (H, W) float32 linear flux in photons/s, NaN where unobserved.
- ``panorama.tif``: the same flux as a float32 TIFF, its second page the validity mask.
- ``panorama.png``: the panorama tone-mapped to 16-bit sRGB, transparent where unobserved.
- ``run.json``: versions, spec, timings per stage and level, per-level statistics and,
  for simulated captures, the accuracy against ground truth.
- ``spec.yaml``: the resolved spec (defaults filled in).
- ``report.html``: a self-contained page of the run (status, warnings, panorama,
  trajectory, levels, spec, versions; :mod:`photonpano.report`).
- ``moving.png``: with a robust compositor, the canvas pixels where it left out a moving
  object's observations (255), 8-bit grey.
- optional: ``level_<k>/`` merged frames, ``trajectory.png``, ``video.mp4``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from .errors import PhotonpanoError
from .faults import interrupts_outside_compilers, unwrapped_interrupts
from .hdr import write_flux_tiff
from .host import PluginHost
from .metrics import ground_truth_report, plot_trajectory, source_trajectory_error
from .outputs import json_default
from .progress import reporting, start_task
from .provenance import run_header
from .reconstruction import reconstruct
from .records import Panorama
from .spec import dump_spec
from .stages import PhotonSource
from .watchdog import guarding

if TYPE_CHECKING:
    from .outputs import Checkpoint, RunFolder
    from .spec_model import PipelineSpec

__all__ = ["RunResult", "prepare_output", "run_pipeline", "reconstruct"]


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
        spec: the validated ``PipelineSpec`` (the plain mapping from :func:`photonpano.api.load_run`
            when the spec's plugins are no longer installed).
        homographies: (T, 3, 3) float64 frame-to-canvas homographies, one per binary
            frame: frame pixel coordinates (x right, y down, pixel centres at integers)
            to panorama canvas pixels (including the super-resolution scale).
        panorama: (Hc, Wc) float32 linear flux of the panorama canvas in photons/s, NaN
            where no frame looked (``panorama.npy``).
        summary: the ``run.json`` content (versions, spec, timings, per-level
            statistics, ground truth report if known).
        out_dir: the output folder, or None for a run kept in memory.
        uncertainty: (T,) float64 predicted 1-sigma error of each binary frame's corner
            positions in panorama pixels (``uncertainty.npy``; inf where nothing
            measured it; :mod:`photonpano.uncertainty`), or None if the run had no
            evidence for it.
    """

    spec: PipelineSpec | dict[str, Any]
    homographies: NDArray[np.float64]
    panorama: NDArray[np.float32]
    summary: dict[str, Any]
    out_dir: Path | None = None
    uncertainty: NDArray[np.float64] | None = None

    def _repr_html_(self) -> str:
        """A notebook's view: status, key figures and a panorama thumbnail (:func:`photonpano.report.summary_html`)."""
        from .report import summary_html

        return summary_html(self.summary, self.panorama)

    def show(self) -> None:
        """Show the run: its report in a notebook, else the panorama in a window (:func:`photonpano.report.show`)."""
        from .report import show

        show(self)


def run_pipeline(spec: PipelineSpec, out_dir: Path | None, host: PluginHost, *, force: bool = False,
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
        PluginHung: a plugin stage call did not return within the limit
            (:mod:`photonpano.watchdog`); the folder is left as after Ctrl-C.
    """
    from .outputs import RunFolder
    from .spec import check_available

    check_available(spec)
    if out_dir is not None and spec.outputs.video:
        from .video_encode import require_av

        require_av()  # before the run, not after it
    # a hung plugin call: PluginHung, outside the folder (kept as on Ctrl-C); Ctrl-C waits while numba loads a kernel
    with guarding(host), reporting(host), interrupts_outside_compilers():
        if out_dir is None:
            with unwrapped_interrupts():
                return _run_into(spec, None, host)
        with RunFolder(out_dir, force=force, resume=resume, inputs=_input_paths(spec)) as folder, \
                unwrapped_interrupts():  # Ctrl-C inside a compiled kernel: an interrupt, checkpoints kept
            return _run_into(spec, folder, host)


def _input_paths(spec: PipelineSpec) -> list[Path]:
    """The existing files and folders named by the spec's source section."""
    return [value for value in vars(spec.source).values() if isinstance(value, Path) and value.exists()]


def _resume_state(folder: RunFolder, spec_text: str) -> Checkpoint | None:
    """Return the checkpoint to continue from (None: start at level 1); the spec must not change."""
    from .outputs import OutputError

    previous = folder.root / "spec.yaml"
    if previous.is_file() and previous.read_text() != spec_text:
        raise OutputError(f"--resume: the spec differs from that of the interrupted run in {previous}; "
                          "resume with the same spec, or pass --force to start anew")
    return folder.last_checkpoint()


def _run_into(spec: PipelineSpec, folder: RunFolder | None, host: PluginHost) -> RunResult:
    """Run ``spec``, writing into ``folder`` (a :class:`~photonpano.outputs.RunFolder`) unless it is None."""
    from .png import write_mask_png, write_panorama_png

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
    frame_sigma = confidence.pop("frame_uncertainty", None)
    hot_pixel_mask = confidence.pop("hot_pixel_mask", None)
    sigma = frame_sigma.sigma_px if frame_sigma is not None else None

    if folder is not None:
        folder.save_npy("homographies.npy", pano.homographies)
        if sigma is not None:
            folder.save_npy("uncertainty.npy", sigma)
        if hot_pixel_mask is not None:
            folder.save_npy("hot_pixels.npy", hot_pixel_mask)
        folder.save_npy("panorama.npy", pano.flux)
        folder.write_with("panorama.tif", lambda path: write_flux_tiff(path, pano.flux))
        if spec.outputs.panorama_png:
            folder.write_with("panorama.png", lambda path: write_panorama_png(path, pano.flux))
        moving = pano.moving
        if moving is not None:
            folder.write_with("moving.png", lambda path: write_mask_png(path, moving))
    host.hook.photonpano_panorama_finished(panorama=pano, spec=spec, source=source, out_dir=out_dir)
    if folder is not None:
        folder.adopt_new_files()  # what observers wrote

    summary: dict[str, Any] = {
        **run_header(spec, host, source),
        **confidence,
        "panorama": {"height": int(pano.flux.shape[0]), "width": int(pano.flux.shape[1]),
                     "observed_fraction": float(np.isfinite(pano.flux).mean()),
                     **({} if pano.moving is None else {"moving_fraction": float(pano.moving.mean())})},
        "levels": stats,
        "timings_s": timings,
    }
    if start is not None:
        summary["resumed_after_level"] = start.level
    error = None
    if source.ground_truth is not None:
        t0 = time.perf_counter()
        advance = progress("ground truth report", source.n_frames) if source.scene_flux is not None else None
        summary["ground_truth"] = ground_truth_report(
            source, homographies, pano, spec.panorama_subbatch_px, compositor=spec.compositor, progress=advance,
            flicker_period_frames=(summary.get("flicker") or {}).get("period_frames"))
        timings["ground_truth_report"] = time.perf_counter() - t0
        error = source_trajectory_error(homographies, source)
    plot = None
    if folder is not None and spec.outputs.trajectory_plot:
        plot = folder.write_with("trajectory.png", lambda path: plot_trajectory(path, homographies, pano.homographies,
                                                                                source, error, sigma))
    if folder is not None and spec.outputs.video:
        from .inpainting import InpaintedSource

        _write_video(folder, source if hot_pixel_mask is None else InpaintedSource(source, hot_pixel_mask), pano,
                     summary, progress)
    host.hook.photonpano_run_finished(spec=spec, summary=summary, out_dir=out_dir)
    if folder is not None and spec.outputs.report:
        from .report import report_html

        page = report_html(json.loads(json.dumps(summary, default=json_default)), pano.flux, pano.homographies,
                           sigma, trajectory=plot.read_bytes() if plot is not None else None,
                           title=f"photonpano run: {folder.root.name}")
        folder.write_text("report.html", page)
    if folder is not None:
        folder.commit(json.dumps(summary, indent=2, default=json_default))
    return RunResult(spec=spec, homographies=pano.homographies, panorama=pano.flux, summary=summary, out_dir=out_dir,
                     uncertainty=sigma)


def _write_video(folder, source: PhotonSource, pano: Panorama, summary: dict[str, Any], progress: Any) -> None:
    """Write ``video.mp4``: the stabilised exposures (``photonpano video``'s defaults) through ``folder``."""
    from .video import default_exposure, encode, exposure_starts, stabilised_frames, white_point

    n = len(pano.homographies)
    exposure = default_exposure(summary, n)
    count = max(1, min(n // exposure, 1000))
    frames = stabilised_frames(source, pano.homographies, pano.flux.shape[:2], exposure,
                               exposure_starts(n, exposure, count, source.frame_step))
    advance = progress("video", count)
    folder.write_with("video.mp4", lambda path: encode(path, frames, count, fps=30.0, white=white_point(pano.flux),
                                                       advance=advance))
