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
- optional: ``level_<k>/`` merged frames, ``trajectory.png``, ``video.mp4``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel

from .errors import PhotonpanoError, StageError
from .executor import Executor
from .hdr import write_flux_tiff
from .host import PluginHost
from .metrics import ground_truth_report, plot_trajectory, source_trajectory_error
from .outputs import json_default
from .progress import reporting, start_task
from .provenance import run_header
from .records import LevelResult, Panorama
from .spec import dump_spec
from .stages import PhotonSource
from .watchdog import guarding, watched

__all__ = ["RunResult", "Stages", "prepare_output", "run_pipeline", "reconstruct"]


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
        uncertainty: (T,) float64 predicted 1-sigma error of each binary frame's corner
            positions in panorama pixels (``uncertainty.npy``; inf where nothing
            measured it; :mod:`photonpano.uncertainty`), or None if the run had no
            evidence for it.
    """

    spec: BaseModel
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
        PluginHung: a plugin stage call did not return within the limit
            (:mod:`photonpano.watchdog`); the folder is left as after Ctrl-C.
    """
    from .outputs import RunFolder
    from .spec import check_available

    check_available(spec)
    if out_dir is not None and spec.outputs.video:
        from .video_encode import require_av

        require_av()  # before the run, not after it
    with guarding(host), reporting(host):  # a hung plugin call: PluginHung, outside the folder (kept as on Ctrl-C)
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
    from .png import write_panorama_png

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
    sigma = frame_sigma.sigma_px if frame_sigma is not None else None

    if folder is not None:
        folder.save_npy("homographies.npy", pano.homographies)
        if sigma is not None:
            folder.save_npy("uncertainty.npy", sigma)
        folder.save_npy("panorama.npy", pano.flux)
        folder.write_with("panorama.tif", lambda path: write_flux_tiff(path, pano.flux))
        if spec.outputs.panorama_png:
            folder.write_with("panorama.png", lambda path: write_panorama_png(path, pano.flux))
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
        error = source_trajectory_error(homographies, source)
    plot = None
    if folder is not None and spec.outputs.trajectory_plot:
        plot = folder.write_with("trajectory.png", lambda path: plot_trajectory(path, homographies, pano.homographies,
                                                                                source, error, sigma))
    if folder is not None and spec.outputs.video:
        _write_video(folder, source, pano, summary, progress)
    host.hook.photonpano_run_finished(spec=spec, summary=summary, out_dir=out_dir)
    if folder is not None and spec.outputs.report:
        from .report import report_html

        page = report_html(json.loads(json.dumps(summary, default=json_default)), pano.flux, pano.homographies,
                           sigma, trajectory=plot.read_bytes() if plot is not None else None,
                           title=f"photonpano run: {out_dir.name}")
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


class Stages:
    """The stages of a spec, built once for one opened capture; used by run, compare and the API.

    Holds the group-size plan, the built resampler, merger, locator (wrapped in the
    binned-frame check when ``group_size: auto``), interpolator and the scheme of each
    level, and runs the levels (:meth:`estimate_motion`) and the panorama (:meth:`compose`).

    Args:
        spec: a validated ``PipelineSpec``.
        source: the opened capture.

    Levels the capture has no room for are dropped with a note (:attr:`notes`), see
    :meth:`_fit_levels`.

    Raises:
        StageError: if the group-size pre-pass cannot read the capture, or the capture is
            too short for even one level.
    """

    def __init__(self, spec: BaseModel, source: PhotonSource) -> None:
        """Build every stage of ``spec`` for ``source``."""
        from .adaptive import plan_group_size
        from .binning import in_merged_pixels, registration_binning
        from .coarse import CascadeLocator
        from .schemes import MosaicScheme, PairwiseScheme
        from .spec import level_schemes

        self.spec, self.source = spec, source
        self.plan = plan_group_size(spec.group_size, source)
        self.binning = registration_binning(spec, source)
        self.locator = in_merged_pixels(spec.locator, self.binning).build()
        if self.plan.auto:  # explicit group sizes keep the plain locator
            # the check bins sensor pixels in blocks of at least 2, counted in merged-frame pixels
            blocks = max(2, self.plan.binning) / self.binning
            self.locator = CascadeLocator(self.locator, max(1, round(blocks)))
        self.resampler, self.merger = spec.resampler.build(), spec.merger.build()
        self.interpolator = spec.interpolator.build()
        built = {"pairwise": PairwiseScheme(self.locator, tuple(spec.pair_offsets)),
                 "mosaic": MosaicScheme(in_merged_pixels(spec.mosaic.locator, self.binning).build,
                                        spec.mosaic.template.build,
                                        subbatch_px=spec.mosaic.subbatch_px,
                                        reject_movers=spec.mosaic.reject_movers)}
        self.schemes = [built[name] for name in level_schemes(spec)]
        self.notes: list[str] = []
        if self.plan.extra_levels:
            self.schemes += [self.schemes[-1]] * self.plan.extra_levels
            self.notes.append(f"groups span whole flicker periods ({self.plan.group_size} frames): "
                              f"{self.plan.extra_levels} more level(s) keep the last level's keyframes as dense")
        self._fit_levels()

    def _fit_levels(self) -> None:
        """Keep the levels the capture has room for, noting any dropped; none at all is an error.

        A resampler that cannot build level k >= 2 for this capture and group size (a
        short clip: the ``midpoint`` groups would be centred less than a frame apart)
        leaves levels 1 .. k-1 to run, with a one-line note in :attr:`notes`.

        Raises:
            StageError: if the resampler cannot build level 1 (e.g. a capture of fewer
                than 4 frames: too short to register anything).
        """
        n, m = self.source.n_frames, self.plan.group_size
        for level in range(1, len(self.schemes) + 1):
            try:
                with watched("resampler", self.resampler, "groups"):
                    self.resampler.groups(n, m, level)
            except ValueError as exc:
                if level == 1:
                    raise StageError("resampler", type(self.resampler).__name__, str(exc)) from None
                planned = len(self.schemes)
                self.schemes = self.schemes[:level - 1]
                self.notes.append(f"a capture of {n} frames in groups of {m} has room for {level - 1} of the "
                                  f"{planned} levels; running {level - 1} ({exc})")
                return

    def estimate_motion(self, executor: Executor, *, on_level: Callable[[LevelResult], None] | None = None,
                        progress: Any = None, resume: Any = None) -> NDArray[np.float64]:
        """Run the levels (:func:`photonpano.levels.estimate_motion`).

        Args:
            executor: where independent work runs.
            on_level: called with each level's frozen :class:`~photonpano.records.LevelResult`.
            progress: ``progress(task, total)`` returning an ``advance(n)`` callable.
            resume: a :class:`~photonpano.outputs.Checkpoint` to continue from (None: level 1).

        Returns:
            (T, 3, 3) float64 frame-to-panorama homographies (middle-frame pixels).
        """
        from .levels import estimate_motion

        start = {} if resume is None else {
            "start_level": resume.level + 1, "initial": resume.homographies}
        return estimate_motion(self.source, self.resampler, self.merger, self.interpolator, self.schemes,
                               group_size=self.plan.group_size, executor=executor,
                               keep_merged=self.spec.outputs.merged_frames, on_level=on_level, progress=progress,
                               binning=self.binning, crosscheck=self.spec.uncertainty, **start)

    def compose(self, homographies: NDArray[np.float64], executor: Executor,
                progress: Callable[[int], None] | None = None) -> Panorama:
        """The panorama of every binary frame by the spec's compositor (:func:`photonpano.compose.compose`)."""
        from .compose import compose

        return compose(self.source, homographies, self.spec.source.panorama_compositor(self.spec.compositor.build),
                       subbatch_px=self.spec.panorama_subbatch_px, progress=progress, executor=executor)

    def level_statistics(self, result: LevelResult) -> dict[str, Any]:
        """One level's ``run.json`` row.

        Its statistics, feature-cache use, ground-truth-free quality figures, the
        binned-frame check's counts and, with ground truth, the RMSE.
        """
        from .coarse import CascadeLocator
        from .metrics import source_trajectory_error
        from .quality import level_figures

        row = result.statistics()
        if result.located.locator_cache is not None:
            row["locator_cache"] = result.located.locator_cache
        row["quality"] = level_figures(result, self.plan, self.source.width, self.source.height)
        if isinstance(self.locator, CascadeLocator) and result.scheme == "pairwise":
            row["registration_check"] = self.locator.take_statistics()
        if self.source.ground_truth is not None:
            row["trajectory_rmse_px"] = source_trajectory_error(result.homographies, self.source).rmse_px
        return row


def reconstruct(spec: BaseModel, source: PhotonSource, *, on_level: Callable[[LevelResult], None] | None = None,
                progress: Any = None, checkpoint: Callable[[Any], None] | None = None, resume: Any = None,
                report: dict[str, Any] | None = None
                ) -> tuple[NDArray[np.float64], list[dict[str, Any]], Panorama, dict[str, float]]:
    """Estimate the motion of ``source`` and composite its panorama as ``spec`` says.

    Args:
        spec: a validated ``PipelineSpec`` (its ``source`` section is not used).
        source: the opened capture.
        on_level: called with each :class:`~photonpano.records.LevelResult`.
        progress: ``progress(task, total)`` returning an ``advance(n)`` callable.
        checkpoint: called with a :class:`~photonpano.outputs.Checkpoint` after each level.
        resume: a :class:`~photonpano.outputs.Checkpoint` to continue from (None: level 1).
        report: filled, if given, with the confidence report of ``run.json``:
            ``status``, ``warnings``, ``notes`` (one line per adjustment the capture
            needed, e.g. fewer levels for a short clip), ``group_size`` (the plan: chosen m and why, see
            :class:`~photonpano.adaptive.GroupPlan`), ``panorama_agreement``
            (:func:`~photonpano.quality.panorama_agreement`), ``uncertainty`` (the
            summary of the per-frame uncertainty, None if there was no evidence) and
            ``frame_uncertainty`` (the :class:`~photonpano.uncertainty.FrameUncertainty`
            itself, or None; not JSON: a caller writing ``run.json`` takes it out) and
            ``flicker`` (:meth:`~photonpano.flicker.Flicker.record` of the flickering
            light found in the photon counts, or None).

    Returns:
        ``(homographies, level_statistics, panorama, timings_s)``: (T, 3, 3) float64
        frame-to-panorama homographies (middle-frame pixels), one statistics dict per
        level (with the trajectory RMSE when the source has ground truth), the
        :class:`~photonpano.records.Panorama` (from the spec's compositor; its
        ``homographies`` map frames to canvas pixels) and wall times in seconds.
    """
    from .executor import make_executor
    from .outputs import Checkpoint
    from .quality import agreement_binning, assess, panorama_agreement
    from .uncertainty import frame_uncertainty

    stats: list[dict[str, Any]] = list(resume.statistics) if resume is not None else []
    stages = Stages(spec, source)
    last: LevelResult | None = None

    def level_done(result: LevelResult) -> None:
        nonlocal last
        last = result
        if on_level is not None:
            on_level(result)
        stats.append(stages.level_statistics(result))
        if checkpoint is not None:
            checkpoint(Checkpoint(result.level, result.homographies, list(stats)))

    timings: dict[str, float] = {}
    with make_executor(spec.executor, spec.workers, spec.dask_address) as executor:
        t0 = time.perf_counter()
        homographies = stages.estimate_motion(executor, on_level=level_done, progress=progress, resume=resume)
        timings["levels"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pano = stages.compose(homographies, executor, progress("panorama", source.n_frames) if progress else None)
        timings["panorama"] = time.perf_counter() - t0
    if report is not None:
        t0 = time.perf_counter()
        plan = stages.plan
        agreement = panorama_agreement(source, stages.merger, homographies, pano, plan.group_size,
                                       agreement_binning(plan))
        uncertainty = frame_uncertainty(last, source.width, source.height) if last is not None else None
        summary = uncertainty.summary(source.frame_rate_hz) if uncertainty is not None else None
        status, warnings = assess(plan, stats, agreement, summary)
        report.update(status=status, warnings=warnings, notes=list(stages.notes), group_size=plan.record(),
                      panorama_agreement=agreement, uncertainty=summary, frame_uncertainty=uncertainty,
                      flicker=plan.flicker.record() if plan.flicker is not None else None)
        timings["confidence"] = time.perf_counter() - t0
    return homographies, stats, pano, timings
