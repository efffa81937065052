"""The stages of a spec for one opened capture, and :func:`reconstruct`: its motion and panorama (nothing written).

:class:`Stages` builds every stage of a spec once for a capture (its photon budget
first, :class:`~photonpano.budget.Budget`) and serves ``run``, ``compare`` and the API;
:func:`reconstruct` runs the levels, the panorama and the confidence report on it.
Writing the output folder is :mod:`photonpano.pipeline`'s.
"""

from __future__ import annotations

import dataclasses
import time
from functools import partial
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from numpy.typing import NDArray

from .errors import StageError
from .executor import Executor
from .flicker import told_of_flicker
from .records import LevelResult, Panorama
from .stages import PhotonSource
from .watchdog import watched

if TYPE_CHECKING:
    from .schemes import LevelScheme
    from .spec_model import PipelineSpec

__all__ = ["Stages", "reconstruct"]


class Stages:
    """The stages of a spec, built once for one opened capture; used by run, compare and the API.

    Holds the capture as every stage reads it (:attr:`source`: its hot and dead pixels
    inpainted where the spec's ``hot_pixels`` found some, :attr:`hot_pixels`, see
    :mod:`photonpano.hot_pixels`), the capture's photon budget (:attr:`budget`, :class:`~photonpano.budget.Budget`),
    the built resampler, merger, locator, interpolator and the scheme of each level (the
    pairwise scheme with the budget's binned check when ``group_size: auto``), and runs
    the levels (:meth:`estimate_motion`, on the capture binned by the budget's
    registration binning) and the panorama (:meth:`compose`).

    Args:
        spec: a validated ``PipelineSpec``.
        source: the opened capture.

    Levels the capture has no room for are dropped with a note (:attr:`notes`), see
    :meth:`_fit_levels`.

    Raises:
        StageError: if the group-size pre-pass cannot read the capture, or the capture is
            too short for even one level.
    """

    def __init__(self, spec: PipelineSpec, source: PhotonSource) -> None:
        """Build every stage of ``spec`` for ``source``."""
        from .budget import Budget, saturation_note
        from .budget.grid import in_merged_pixels
        from .budget.probe import short_of_light
        from .hot_pixels import with_hot_pixels_inpainted
        from .schemes import PairCheck, PairwiseScheme
        from .spec import level_schemes

        source, self.hot_pixels = with_hot_pixels_inpainted(source, spec.hot_pixels)
        self.spec, self.source = spec, source
        self.budget = budget = Budget.for_capture(spec, source)
        self.locator = in_merged_pixels(spec.locator, budget.register_binning).build()
        check = PairCheck(budget.check_binning) if budget.check_binning is not None else None
        self.resampler, self.merger = spec.resampler.build(), spec.merger.build()
        self.interpolator = spec.interpolator.build()
        advice = "" if budget.plan.auto else (
            f" (group_size {budget.group_size} is set in the spec, so the pairs were not checked on binned "
            "frames; with group_size: auto they are, and those the locator cannot register are registered again)")
        saturated = saturation_note(budget.plan.probe)
        advice += f"; {saturated}" if saturated else ""
        built = {"pairwise": PairwiseScheme(self.locator, tuple(spec.pair_offsets), check, advice,
                                            turning_camera=spec.camera_model == "auto"),
                 "mosaic": self._mosaic_scheme()}
        self.schemes = [built[name] for name in level_schemes(spec)]
        self.notes: list[str] = []
        plan = budget.plan
        if plan.extra_levels:
            self.schemes += [self.schemes[-1]] * plan.extra_levels
            self.notes.append(f"groups span whole flicker periods ({plan.group_size} frames): "
                              f"{plan.extra_levels} more level(s) keep the last level's keyframes as dense")
        if self.hot_pixels is not None and self.hot_pixels.mask.any():
            found = self.hot_pixels
            self.notes.append(f"hot pixels: {found.hot} hot and {found.dead} dead pixels "
                              f"({found.mask.mean():.2%} of the sensor) inpainted from their neighbours (hot_pixels)")
        if (note := short_of_light(plan, source.n_frames)) is not None:
            self.notes.append(note)
        self._fit_levels()

    def _mosaic_scheme(self) -> LevelScheme:
        """The spec's mosaic scheme, registering at the budget's ``mosaic_binning``."""
        from .budget.grid import in_merged_pixels
        from .schemes import MosaicScheme
        from .schemes.mosaic import MOVERS_SIGMAS
        from .schemes.settings import affine_from_level, affine_locator, robust_template

        mosaic, binning, flicker = self.spec.mosaic, self.budget.mosaic_binning, self.budget.plan.flicker
        affine = affine_locator(mosaic.locator)
        return MosaicScheme(in_merged_pixels(mosaic.locator, binning).build,
                            told_of_flicker(mosaic.template.build, flicker), subbatch_px=mosaic.subbatch_px,
                            reject_movers=MOVERS_SIGMAS if mosaic.reject_movers == "auto" else mosaic.reject_movers,
                            make_robust=told_of_flicker(robust_template(mosaic).build, flicker),
                            detect_movers=mosaic.reject_movers == "auto", holdout=mosaic.holdout,
                            correct_bias=mosaic.correct_template_bias,
                            per_parameter_priors=mosaic.template_bias_priors == "per-parameter",
                            make_chain_locator=in_merged_pixels(mosaic.locator.converging(), binning).build,
                            make_affine_locator=None if affine is None else in_merged_pixels(affine, binning).build,
                            affine_from_level=affine_from_level(self.spec) if affine is not None else None)

    def mosaic_at_full_resolution(self, reason: str) -> None:
        """Register the mosaic levels at full resolution from now on (budget ``mosaic_binning`` 1, because ``reason``).

        They get a new scheme (its mover decision taken afresh); all else stays as it is.
        """
        self.budget = dataclasses.replace(self.budget, mosaic_binning=1, mosaic_reason=reason)
        mosaic = self._mosaic_scheme()
        self.schemes = [mosaic if scheme.needs_template else scheme for scheme in self.schemes]

    def _fit_levels(self) -> None:
        """Keep the levels the capture has room for, noting any dropped; none at all is an error.

        A resampler that cannot build level k >= 2 for this capture and group size (a
        short clip: the ``midpoint`` groups would be centred less than a frame apart)
        leaves levels 1 .. k-1 to run, with a one-line note in :attr:`notes`.

        Raises:
            StageError: if the resampler cannot build level 1 (e.g. a capture of fewer
                than 4 frames: too short to register anything).
        """
        n, m = self.source.n_frames, self.budget.group_size
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

        A scheme whose registration binning k is above 1 (the budget's
        ``register_binning`` for pairwise levels, ``mosaic_binning`` for mosaic ones) runs
        on the capture binned k x k (:class:`~photonpano.schemes.Binned`, one grid per k
        and call). Where ``auto`` binned the mosaic levels for the capture's length alone
        and level 1 finds a scene of little texture (:func:`~photonpano.budget.binnings.little_texture`),
        they register at full resolution instead.

        Args:
            executor: where independent work runs.
            on_level: called with each level's frozen :class:`~photonpano.records.LevelResult`.
            progress: ``progress(task, total)`` returning an ``advance(n)`` callable.
            resume: a :class:`~photonpano.outputs.Checkpoint` to continue from (None: level 1).

        Returns:
            (T, 3, 3) float64 frame-to-panorama homographies (middle-frame pixels).
        """
        from .budget.binnings import full_resolution_hint, little_texture
        from .budget.grid import RegistrationGrid
        from .levels import estimate_motion
        from .schemes import Binned

        start = {} if resume is None else {"start_level": resume.level + 1, "initial": resume.homographies}
        grids: dict[int, RegistrationGrid] = {}
        wrapped: dict[int, LevelScheme] = {}

        def binned(scheme: LevelScheme) -> LevelScheme:
            k = self.budget.mosaic_binning if scheme.needs_template else self.budget.register_binning
            if k == 1:
                return scheme
            if k not in grids:
                grids[k] = RegistrationGrid(self.source, k)
            return wrapped.setdefault(id(scheme), Binned(scheme, grids[k]))

        binned_for_length = resume is None and full_resolution_hint(
            self.spec, self.source, self.budget.mosaic_binning, self.budget.plan.photons_per_pixel_per_group)

        def revise(result: LevelResult) -> list[LevelScheme] | None:
            """After level 1 of a scene of little texture, the mosaic levels at full resolution."""
            if result.level != 1 or not binned_for_length or (reason := little_texture(result.located)) is None:
                return None
            self.mosaic_at_full_resolution(reason)
            self.notes.append(f"{reason.removeprefix('auto: ')} (mosaic.registration_binning: auto)")
            return [binned(scheme) for scheme in self.schemes]

        schemes = [binned(scheme) for scheme in self.schemes]
        return estimate_motion(self.source, self.resampler, self.merger, self.interpolator, schemes,
                               group_size=self.budget.group_size, executor=executor,
                               keep_merged=self.spec.outputs.merged_frames, on_level=on_level, progress=progress,
                               crosscheck=self.spec.uncertainty or self.spec.mosaic.correct_shape_drift,
                               correct_shape_drift=self.spec.mosaic.correct_shape_drift, revise=revise, **start)

    def compose(self, homographies: NDArray[np.float64], executor: Executor,
                progress: Callable[[int], None] | None = None) -> Panorama:
        """The panorama of every binary frame by the spec's compositor (:func:`photonpano.compose.compose`).

        A super-resolved canvas whose frames the motion did not dither adds
        :func:`~photonpano.compose.dither_note` to :attr:`notes`.
        """
        from .compose import compose, dither_note

        build = told_of_flicker(partial(self.spec.source.panorama_compositor, self.spec.compositor.build),
                                self.budget.plan.flicker)
        pano = compose(self.source, homographies, build(), subbatch_px=self.spec.panorama_subbatch_px,
                       progress=progress, executor=executor)
        dither = dither_note(pano.homographies, self.source.width, self.source.height, self.spec.scale)
        if dither is not None:
            self.notes.append(dither)
        return pano

    def level_statistics(self, result: LevelResult) -> dict[str, Any]:
        """One level's ``run.json`` row.

        Its statistics, feature-cache use, ground-truth-free quality figures, the
        binned-frame check's counts and, with ground truth, the RMSE.
        """
        from .metrics import source_trajectory_error
        from .quality import level_figures

        row = result.statistics()
        if result.located.locator_cache is not None:
            row["locator_cache"] = result.located.locator_cache
        row["quality"] = level_figures(result, self.budget.plan, self.source.width, self.source.height)
        if result.located.check is not None:
            row["registration_check"] = result.located.check
        if result.located.movers is not None:
            row["movers"] = result.located.movers
        if result.located.template_bias is not None:
            row["template_bias"] = result.located.template_bias
        if self.source.ground_truth is not None:
            row["trajectory_rmse_px"] = source_trajectory_error(result.homographies, self.source).rmse_px
        return row


def reconstruct(spec: PipelineSpec, source: PhotonSource, *, on_level: Callable[[LevelResult], None] | None = None,
                progress: Any = None, checkpoint: Callable[[Any], None] | None = None, resume: Any = None,
                report: dict[str, Any] | None = None
                ) -> tuple[NDArray[np.float64], list[dict[str, Any]], Panorama, dict[str, float]]:
    """Estimate the motion of ``source`` and composite its panorama as ``spec`` says.

    Args:
        spec: a validated ``PipelineSpec`` (its ``source`` section is not used).
        source: the opened capture.
        on_level: called with each :class:`~photonpano.records.LevelResult` (levels 2.. twice
            where binned mosaic levels left frames predicted above the uncertainty's limit,
            or one registered none of its frames, and they ran again at full resolution;
            ``budget.binnings.full_resolution_hint``).
        progress: ``progress(task, total)`` returning an ``advance(n)`` callable.
        checkpoint: called with a :class:`~photonpano.outputs.Checkpoint` after each level.
        resume: a :class:`~photonpano.outputs.Checkpoint` to continue from (None: level 1).
        report: filled, if given, with the confidence report of ``run.json``:
            ``status``, ``warnings``, ``notes`` (one line per adjustment the capture
            needed, e.g. fewer levels for a short clip), ``group_size`` (the plan: chosen m and why, see
            :class:`~photonpano.budget.GroupPlan`), ``budget`` (:meth:`~photonpano.budget.Budget.record`:
            the group size and the three binnings, each with why), ``panorama_agreement``
            (:func:`~photonpano.quality.panorama_agreement`), ``uncertainty`` (the
            summary of the per-frame uncertainty, None if there was no evidence) and
            ``frame_uncertainty`` (the :class:`~photonpano.uncertainty.FrameUncertainty`
            itself, or None; not JSON: a caller writing ``run.json`` takes it out) and
            ``flicker`` (:meth:`~photonpano.flicker.Flicker.record` of the flickering
            light found in the photon counts, or None) and ``movers`` (the mosaic levels'
            mover rejection, :func:`~photonpano.quality.movers_record`; None where it is off) and
            ``hot_pixels`` (:meth:`~photonpano.hot_pixels.HotPixels.record`, None with
            ``hot_pixels: off``) and ``hot_pixel_mask`` ((H, W) bool pixels inpainted, or
            None where none was; not JSON: a caller writing ``run.json`` takes it out).

    Returns:
        ``(homographies, level_statistics, panorama, timings_s)``: (T, 3, 3) float64
        frame-to-panorama homographies (middle-frame pixels), one statistics dict per
        level (with the trajectory RMSE when the source has ground truth), the
        :class:`~photonpano.records.Panorama` (from the spec's compositor; its
        ``homographies`` map frames to canvas pixels) and wall times in seconds.
    """
    from .budget.binnings import full_resolution_hint
    from .executor import make_executor
    from .outputs import Checkpoint
    from .quality import assess, movers_record, panorama_agreement
    from .uncertainty import frame_uncertainty

    stats: list[dict[str, Any]] = list(resume.statistics) if resume is not None else []
    stages = Stages(spec, source)
    last: LevelResult | None = None
    # each scheme's earliest trajectory after level 1, for the level-change term of the uncertainty
    # (how far the levels of the last level's scheme moved the frames since its first refining
    # level; a resumed run starts from the last finished level's)
    first_of_scheme: dict[str, NDArray[np.float64]] = {}
    if resume is not None and len(stats) >= 2 and stats[-1].get("scheme"):
        first_of_scheme[stats[-1]["scheme"]] = resume.homographies
    level_one_span: tuple[int, int] | None = None  # level 1's first and last reference frame (not known on resume)
    level_one: NDArray[np.float64] | None = None

    def level_done(result: LevelResult) -> None:
        nonlocal last, level_one_span, level_one
        last = result
        if result.level == 1 and len(result.groups):
            level_one_span = (int(result.groups.reference[0]), int(result.groups.reference[-1]))
            level_one = result.homographies
        if result.level >= 2:
            first_of_scheme.setdefault(result.scheme, result.homographies)
        if on_level is not None:
            on_level(result)
        stats.append(stages.level_statistics(result))
        if checkpoint is not None:
            checkpoint(Checkpoint(result.level, result.homographies, list(stats)))

    def uncertainty_now() -> Any:
        """The per-frame uncertainty of the last level so far (None before a level or without evidence)."""
        if last is None:
            return None
        chain = stats[0].get("quality", {}).get("pose_graph_residual_px") if stats else None
        # the level-change term compares iterations of one scheme after level 1: the level after
        # level 1 moves the frames by level 1's error, not by the error left after it; and the move
        # since the scheme's first such level, not the last step alone, which shrinks with every
        # level added where convergence is slow (a fourth level hid a dark scene's 0.86 px error)
        first = first_of_scheme.get(last.scheme)
        return frame_uncertainty(last, source.width, source.height, chain,
                                 previous=None if first is last.homographies else first, level_one_span=level_one_span)

    timings: dict[str, float] = {}
    def binned_for_length() -> str | None:
        """``full_resolution_hint``'s line where the mosaic levels are binned for the capture's length alone."""
        return full_resolution_hint(spec, stages.source, stages.budget.mosaic_binning,
                                    stages.budget.plan.photons_per_pixel_per_group)

    with make_executor(spec.executor, spec.workers, spec.dask_address) as executor:
        t0 = time.perf_counter()
        failed: str | None = None  # why a binned mosaic level registered nothing
        try:
            homographies = stages.estimate_motion(executor, on_level=level_done, progress=progress, resume=resume)
        except StageError as exc:
            failed = exc.reason if exc.plugin == "mosaic" else None
            if failed is None or level_one is None or not binned_for_length():
                raise
        found = None
        if not failed and level_one is not None and len(stats) > 1 and binned_for_length():
            found = uncertainty_now()
        above = found.summary(source.frame_rate_hz)["above_limit"] if found is not None else []
        if (failed or above) and level_one is not None:  # the binned mosaic levels again at full resolution
            binned = stages.budget.mosaic_binning
            if failed:
                why, what = failed, f"failed ({failed})"
            else:
                worst = f"{max(e['max_px'] or 0.0 for e in above):.2g} px"
                why, what = (f"the held-out registrations predicted errors up to {worst}",
                             f"left frames predicted up to {worst} off")
            stages.mosaic_at_full_resolution(f"auto: binned {binned}x{binned} for the capture's length, {why}: "
                                             "registered again at full resolution")
            stages.notes.append(f"the mosaic levels, binned {binned}x{binned} to save time on this long capture, "
                                f"{what}: they ran again at full resolution from level 1 "
                                "(mosaic.registration_binning: auto)")
            del stats[1:]
            first_of_scheme.clear()
            last = found = None
            again = (lambda task, total: progress(f"{task}, full resolution", total)) if progress else None
            homographies = stages.estimate_motion(executor, on_level=level_done, progress=again,
                                                  resume=Checkpoint(1, level_one, list(stats)))
        timings["levels"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pano = stages.compose(homographies, executor, progress("panorama", source.n_frames) if progress else None)
        timings["panorama"] = time.perf_counter() - t0
    if report is not None:
        t0 = time.perf_counter()
        budget = stages.budget
        plan = budget.plan
        agreement = panorama_agreement(stages.source, stages.merger, homographies, pano, plan.group_size,
                                       budget.agreement_binning)
        uncertainty = found if found is not None else uncertainty_now()
        summary = uncertainty.summary(source.frame_rate_hz) if uncertainty is not None else None
        status, warnings = assess(plan, stats, agreement, summary)
        movers = movers_record(stats)
        notes = list(stages.notes)
        hint = binned_for_length()
        if status == "degraded" and hint is not None:
            notes.append(hint)
        if movers is not None and movers["engaged"]:
            notes.append(f"moving objects: the robust template of level {movers['level']} left out a region of "
                         f"{movers['largest_region']:.1%} of the canvas; pixels disagreeing with the panorama "
                         "were left out of the mosaic levels' registrations (mosaic.reject_movers)")
        report.update(status=status, warnings=warnings, notes=notes, group_size=plan.record(), movers=movers,
                      budget=budget.record(),
                      panorama_agreement=agreement, uncertainty=summary, frame_uncertainty=uncertainty,
                      flicker=plan.flicker.record() if plan.flicker is not None else None,
                      hot_pixels=stages.hot_pixels.record() if stages.hot_pixels is not None else None,
                      hot_pixel_mask=stages.hot_pixels.mask if stages.hot_pixels is not None
                      and stages.hot_pixels.mask.any() else None)
        timings["confidence"] = time.perf_counter() - t0
    return homographies, stats, pano, timings
