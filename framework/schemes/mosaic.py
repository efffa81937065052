"""The ``mosaic`` level scheme: each merged frame against the panorama of the current estimate.

Frame-to-mosaic alignment (Szeliski, "Image Alignment and Stitching", 2006, Sec. 6.2;
Sawhney and Kumar, 1999): once an estimate exists, every binary frame is composited onto
one canvas (the *template*, through a compositor), and each merged frame is registered
against that panorama resampled into its reference frame's grid
(:func:`~photonpano.views.panorama_views`). The template is a low-noise average over
the whole capture, so registrations do not chain (no drift, no pose graph) and each group
is registered once.

Every mosaic level composites its template afresh from the photons with the estimate it starts from (the
interpolated, smoothed trajectory). Building the next level's template from this level's merged frames at
their registered positions instead saves that pass but copies each registration's error into the template, and
a later level then gains little or loses (level 3 of four suite photographs' base captures, that way and from
the photons: objects_coffee 0.24 -> 0.18 px, outdoor_camera 0.21 -> 0.17, landscape_mountains 0.13 -> 0.11,
text_handwriting 0.16 -> 0.16).

A template made from every photon pulls each registration toward the estimate it corrects; ``holdout`` (spec
``mosaic.holdout``, off by default) registers each group against a leave-one-out template instead
(:mod:`photonpano.schemes.holdout`).

Groups go to the executor in windows; each window is a pure task (it builds its own locator and returns what
it found), so the windows can run on threads or processes. From ``affine_from_level`` on (spec
``mosaic.perspective_levels``) the windows register affine corrections: the perspective terms are the least
determined of a registration against the panorama, and each level's bias in them adds up.

A scene is rarely static: with ``reject_movers`` (spec ``mosaic.reject_movers``), pixels
of a merged frame that disagree with the panorama view by more than that many robust
standard deviations (a passing object, or the ghost of one that the previous estimate's
panorama still holds) are left out of its registration and its held-out cross-check
(:func:`mask_disagreement`; the robustness term of burst merging: Hasinoff et al., "Burst
photography for high dynamic range and low-light imaging on mobile cameras", SIGGRAPH
Asia 2016, Sec. 5, and Wronski et al., "Handheld multi-frame super-resolution", SIGGRAPH
2019, Sec. 5), and so is where the robust template (:mod:`photonpano.robust_merge`: a
mover never enters it) left out the exposures its frames fall in
(:func:`~photonpano.robust_merge.left_out_in_frames`: the mover meanwhile, even where it
barely stands out of the merged frame). The disagreement test also untrusts the regions
of a static scene that the current estimate misregisters, so by default (``detect_movers``)
it engages only where a mover is found: the first mosaic level composites its template
robustly and, if the robust merge left out exposures over one connected region of at
least :data:`MOVERS_MIN_FRACTION` of the covered canvas (:func:`moving_fraction`: a
mover's path is one region, a slightly misregistered estimate leaves many small ones),
rejection engages for that level and the next; otherwise the template is composited
plainly, as without ``reject_movers``, and so are the next levels' (a static scene's run
is bit-identical to one with rejection off). The decision and the fractions go to
:attr:`~photonpano.records.LocateResult.movers` (``run.json``'s ``movers``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from .. import geometry
from ..binomial import binary_exposure, stabilised_detections
from ..compose import BilinearCompositor, compose
from ..errors import StageError
from ..executor import pure_task
from ..guards import bridge, plausible
from ..information import homography_information
from ..locator import Locator, LocatorContext
from ..long_pairs import links_both_ways, long_baseline_chains, register_links
from ..movers import moving_fraction
from ..records import LocateResult, MergedFrames, PairRegistrations, Panorama
from ..robust_merge import left_out_in_frames
from ..stages import Compositor
from ..views import panorama_views
from ..watchdog import watched
from .base import LevelScheme, LevelTask
from .holdout import HoldoutTemplate
from .template_bias import correct_template_bias

__all__ = ["MOVERS_MIN_FRACTION", "MOVERS_SIGMAS", "MosaicScheme", "mask_disagreement", "moving_fraction"]

MOVERS_SIGMAS = 5.0
"""The disagreement threshold of ``reject_movers: auto``, in robust standard deviations."""

MOVERS_MIN_FRACTION = 0.05
"""Fraction of the covered canvas that the largest region the robust template left out must reach
for mover rejection to engage: the suite's static captures reach at most 1.5 % (the outdoor
camera, 100 000 frames; 0.9 % the others; the robust merge's 10 % tolerance), a disc of radius
30 px crossing at 0.08 px/frame 20-21 %."""


@dataclass(frozen=True)
class _WindowResult:
    """What one window of groups returns (see :meth:`MosaicScheme.locate`)."""

    registrations: PairRegistrations
    cache: dict[str, int]
    merge_s: float
    total_s: float
    merged: MergedFrames | None
    crosscheck: PairRegistrations | None = None
    information: NDArray[np.float64] | None = None


class MosaicScheme(LevelScheme):
    """Register every merged frame of a level against the panorama of the current estimate.

    Args:
        make_locator: builds a locator (called once per window of groups).
        make_compositor: builds the template's compositor (e.g. ``flux-canvas``'s config ``build``).
        subbatch_px: sub-batch tolerance of that template, in canvas pixels.
        window: groups merged and registered per task.
        reject_movers: robust standard deviations beyond which pixels disagreeing with
            the panorama view are left out (:func:`mask_disagreement`); None: off.
        make_robust: builds the robust version of the template compositor (used while
            rejection is on); None: ``make_compositor``'s.
        detect_movers: engage ``reject_movers`` only where the first mosaic level's robust
            template finds a mover (see the module); False: always.
        correct_bias: correct each registration for the template's own error
            (:mod:`photonpano.schemes.template_bias`; not with a ``holdout`` template).
        per_parameter_priors: that correction's error model has a prior per homography
            parameter (False: one for all 8).
        holdout: runs of consecutive frames the plain template is cut into; each group is
            registered against the runs its frames do not fall in (:class:`~photonpano.schemes.holdout.HoldoutTemplate`;
            templates from ``flux-canvas``, i.e. :class:`~photonpano.compose.BilinearCompositor`,
            only: another compositor's template holds every photon). 1 (the default): every
            photon.
        make_chain_locator: builds the held-out chains' locator (:mod:`photonpano.long_pairs`); None: ``make_locator``.
        make_affine_locator: builds the locator of the levels from ``affine_from_level`` on (affine corrections).
        affine_from_level: the first level (1-based, of all levels) registered by ``make_affine_locator``; None: none.
    """

    name = "mosaic"
    needs_template = True

    def __init__(self, make_locator: Callable[[], Locator], make_compositor: Callable[[], Compositor], *,
                 subbatch_px: float = 0.5, window: int = 16, reject_movers: float | None = None,
                 make_robust: Callable[[], Compositor] | None = None, detect_movers: bool = False,
                 holdout: int = 1, correct_bias: bool = False, per_parameter_priors: bool = False,
                 make_chain_locator: Callable[[], Locator] | None = None,
                 make_affine_locator: Callable[[], Locator] | None = None,
                 affine_from_level: int | None = None) -> None:
        """Create the scheme from factories of its locator and template compositor."""
        self.holdout, self.correct_bias, self.per_parameter_priors = holdout, correct_bias, per_parameter_priors
        self.make_affine_locator, self.affine_from_level = make_affine_locator or make_locator, affine_from_level
        self.reject_movers, self.detect_movers = reject_movers, detect_movers
        self.make_locator, self.make_chain_locator = make_locator, make_chain_locator or make_locator
        self.make_compositor, self.make_robust = make_compositor, make_robust or make_compositor
        self.subbatch_px, self.window = subbatch_px, window
        self._engaged: dict[tuple[int, int], bool] = {}  # detect_movers' decision per capture (first mosaic level)

    def _affine(self, level: int) -> bool:
        """Whether ``level`` (1-based) registers affine corrections (``affine_from_level``)."""
        return self.affine_from_level is not None and level >= self.affine_from_level

    def template(self, task: LevelTask) -> tuple[Panorama | HoldoutTemplate, dict[str, Any] | None]:
        """The panorama the task's merged frames are registered against, and the level's mover record.

        Every binary frame at its current estimate, composited in this process: on the
        run's threads, serially with a Dask executor (which would ship the capture to its
        workers for it); the same template either way. Robust where mover
        rejection is on; with ``detect_movers`` the first call for a capture decides
        that for the later ones (see the module).

        Returns:
            ``(template, movers)``: the :class:`Panorama` (a :class:`HoldoutTemplate` where
            ``holdout`` applies and rejection is off) and the record that goes to
            :attr:`~photonpano.records.LocateResult.movers` (``engaged``, ``detected``,
            ``template_fraction``, ``largest_region``), None with ``reject_movers`` off.
        """
        executor = task.executor if task.executor.in_process else None

        def build(compositor: Compositor) -> Panorama:
            return compose(task.source, task.homographies, compositor, subbatch_px=self.subbatch_px, executor=executor)

        def plain() -> Panorama | HoldoutTemplate:
            compositor = self.make_compositor()
            if self.holdout < 2 or type(compositor) is not BilinearCompositor:
                return build(compositor)
            runs = BilinearCompositor(compositor.scale, self.holdout)
            build(runs)
            return HoldoutTemplate(runs, task.source)

        if self.reject_movers is None:
            return plain(), None
        if not self.detect_movers:
            pano = build(self.make_robust())
            return pano, {"engaged": True, "detected": None, **_fractions(pano)}
        key = (id(task.source), task.source.n_frames)
        if key in self._engaged:  # decided at the first mosaic level
            if not self._engaged[key]:
                return plain(), {"engaged": False, "detected": False, **_fractions(None)}
            pano = build(self.make_robust())
            return pano, {"engaged": True, "detected": False, **_fractions(pano)}
        pano = build(self.make_robust())
        found = _fractions(pano)
        engaged = self._engaged[key] = bool(found["largest_region"] is not None
                                            and found["largest_region"] >= MOVERS_MIN_FRACTION)
        return (pano if engaged else plain()), {"engaged": engaged, "detected": True, **found}

    def locate(self, task: LevelTask) -> LocateResult:
        """Register each merged frame against the template (see the module).

        Returns:
            G registrations (merged frame pixels to panorama-view pixels) and keyframes
            (failed registrations bridged from their neighbours).

        Raises:
            StageError: if no merged frame could be registered.
        """
        source, groups, current = task.source, task.groups, task.current
        template, movers = self.template(task)
        if isinstance(template, HoldoutTemplate):
            template.prepare(groups.start, groups.stop)
        reject = self.reject_movers if movers is not None and movers["engaged"] else None
        to_canvas = template.homographies[groups.reference]
        robust = template if isinstance(template, Panorama) else None  # its exposures left out: the mover's path
        rejected, ranges = (None, None) if robust is None else (robust.rejected, robust.exposure_ranges)

        def prepare(index: NDArray[np.int64]) -> tuple[MergedFrames, MergedFrames, float]:
            """The groups' merged frames (movers left out), their panorama views and the merge's seconds."""
            start = time.perf_counter()
            with watched("merger", task.merger, "merge"):
                merged = task.merger.merge(source, task.homographies, groups.select(index))
            merge_s = time.perf_counter() - start
            if isinstance(template, HoldoutTemplate):
                views = template.views(groups.start[index], groups.stop[index], to_canvas[index], source.height,
                                       source.width, task.group_size, binary_exposure(source))
            else:
                views = panorama_views(template, to_canvas[index], source.height, source.width, task.group_size,
                                       binary_exposure(source))
            if reject is not None:
                merged = mask_disagreement(merged, views, reject)
                if rejected is not None and ranges is not None:  # the mover meanwhile
                    merged = dataclasses.replace(merged, masks=merged.masks & ~left_out_in_frames(
                        rejected, ranges, groups.start[index], groups.stop[index], to_canvas[index],
                        merged.masks.shape[-2:]))
            return merged, views, merge_s

        @pure_task
        def run(index: NDArray[np.int64]) -> _WindowResult:
            start = time.perf_counter()
            locator = (self.make_affine_locator if self._affine(task.level) else self.make_locator)()
            n = len(index)
            cross_checked = task.crosscheck and n > 1
            # the held-out pairs register the merged frames again: named by ids, each is
            # prepared once (the locator's content cache); without them no frame returns
            context = LocatorContext(reuses_frames=cross_checked)
            merged, views, merge_s = prepare(index)
            if cross_checked:
                merged = dataclasses.replace(merged, ids=MergedFrames.new_ids(n))
                views = dataclasses.replace(views, ids=MergedFrames.new_ids(n))
            found = locator.register_to_template(views, merged, np.repeat(np.eye(3)[None], n, axis=0), context)
            information = homography_information(_noise_even(views.flux, views.exposure_s), views.masks & merged.masks)
            cross = None
            if cross_checked:  # held out: consecutive merged frames against each other
                names = merged.frame_ids()
                cross = locator.register_pairs(merged, np.stack([names[:-1], names[1:]], axis=1), geometry.normalize(
                    np.linalg.inv(current[index[:-1]]) @ current[index[1:]]), context)
            return _WindowResult(found, locator.cache_stats(), merge_s, time.perf_counter() - start,
                                 merged if task.keep_merged else None, cross, information)

        windows = [np.arange(s, min(s + self.window, len(groups))) for s in range(0, len(groups), self.window)]
        chains = (long_baseline_chains(current, groups.stop - groups.start, source.width, source.height)
                  if task.crosscheck else np.zeros((0, 3), np.int64))
        expected = geometry.normalize(np.linalg.inv(current[chains[:, 1]]) @ current[chains[:, 2]])
        joined, positions = np.unique(chains[:, 1:], return_inverse=True)

        @pure_task
        def link(backward: bool) -> PairRegistrations:
            """The held-out chains' links registered one way (long_pairs.register_links)."""
            return register_links(self.make_chain_locator(), prepare(joined)[0], positions.reshape(-1, 2), expected,
                                  backward=backward)

        started = time.perf_counter()
        done = None if task.progress is None else (lambda part: task.progress(len(part.registrations)))
        parts: list[_WindowResult] = task.executor.map(run, windows, done=done)
        ways = task.executor.map(link, [False, True]) if len(chains) else None  # both ways, on two workers
        links = None if ways is None else links_both_ways(ways[0], ways[1], expected, source.width, source.height)
        wall = time.perf_counter() - started
        regs = PairRegistrations.concat(*(part.registrations for part in parts))
        ok = regs.ok & plausible(regs.homographies, source.width, source.height)
        if not ok.any():
            raise StageError("locator", "mosaic", f"level {task.level}: none of the {len(ok)} merged frames "
                             "registered against the panorama of the current estimate")
        regs = regs.with_ok(ok)
        bias = None
        if self.correct_bias and isinstance(template, Panorama) and template.flux.ndim == 2:
            exposure = binary_exposure(source)
            image = template.flux if exposure is None else stabilised_detections(template.flux, exposure)
            corrected, found = correct_template_bias(template.homographies, image, groups.start, groups.stop,
                                                     groups.reference, regs.homographies, ok, source.width,
                                                     source.height, per_parameter_priors=self.per_parameter_priors,
                                                     affine=self._affine(task.level))
            regs, bias = dataclasses.replace(regs, homographies=corrected), found.record()
        keyframes = bridge(current, geometry.normalize(current @ regs.homographies), ok)
        cache: dict[str, int] = {}
        for part in parts:
            for key, value in part.cache.items():
                cache[key] = cache.get(key, 0) + value
        # merging and registering interleave on the workers: apportion the wall time
        busy = sum(part.total_s for part in parts)
        merge_s = wall * sum(part.merge_s for part in parts) / busy if busy else 0.0
        merged = MergedFrames.concat(*(part.merged for part in parts)) if task.keep_merged else None
        cross, cross_index = None, None
        if task.crosscheck:
            cross = PairRegistrations.concat(*(p.crosscheck for p in parts if p.crosscheck is not None))
            cross_index = np.concatenate([np.zeros((0, 2), np.int64)] + [
                np.stack([w[:-1], w[1:]], axis=1) for w in windows if len(w) > 1])
        information = np.concatenate([part.information for part in parts])
        information[~ok] = 0.0
        return LocateResult(keyframes, regs, None, merged=merged, merge_s=merge_s, locator_cache=cache or None,
                            crosscheck=cross, crosscheck_index=cross_index, chain=links,
                            chain_index=None if links is None else chains, movers=movers, information=information,
                            template_bias=bias)


def _noise_even(flux: NDArray[np.float32], exposure_s: float | None) -> NDArray[np.float32]:
    """Flux (photons/s) as the locators register it: stabilised for binary frames of ``exposure_s`` s; None: as is."""
    return flux if exposure_s is None else stabilised_detections(flux, exposure_s)


def _fractions(pano: Panorama | None) -> dict[str, float | None]:
    """``template_fraction`` and ``largest_region`` of :func:`moving_fraction` (None each without a mask)."""
    total, largest = (moving_fraction(pano) if pano is not None else None) or (None, None)
    return {"template_fraction": total, "largest_region": largest}


def mask_disagreement(merged: MergedFrames, views: MergedFrames, sigmas: float = 5.0, grow_sigmas: float = 2.0,
                      smooth_px: float = 2.0, margin_px: int = 3, min_width_px: int = 9) -> MergedFrames:
    """Untrust the pixels of merged frames that disagree with the panorama at their pose.

    Each frame is compared with its view scaled by the frame's gain (the ratio of the
    medians over pixels both trust) on the scale the locators register, where the noise
    is the same at every flux (:func:`_noise_even`: stabilised detections for binary
    frames). Their difference, smoothed by a Gaussian of ``smooth_px``, is tested against
    ``sigmas`` times its robust standard deviation (1.4826 x median absolute value), and a
    morphological opening by a disc ``min_width_px`` wide drops the thin candidates (a
    misregistered edge) and the points (a misregistered star). What is left grows into the
    connected pixels beyond ``grow_sigmas`` (hysteresis thresholding: Canny, "A
    computational approach to edge detection", PAMI 1986): a mover is smeared along its
    path over a group's frames, and the faint ends of the smear still pull a registration.
    A margin of ``margin_px`` is untrusted around it. On flux, whose noise grows with it,
    the test untrusted the bright regions of static high-contrast scenes, and a growth
    there floods them (measured in docs/real_scenes.md).

    Args:
        merged: G merged frames (flux in photons/s, NaN where unobserved).
        views: the panorama resampled into the same G grids
            (:func:`~photonpano.views.panorama_views`).
        sigmas: threshold in robust standard deviations.
        grow_sigmas: threshold the disagreeing regions grow to, in robust standard deviations.
        smooth_px: Gaussian sigma of the smoothing, in pixels.
        margin_px: dilation of the untrusted pixels, in pixels.
        min_width_px: narrowest disagreeing region untrusted, in pixels.

    Returns:
        ``merged`` with ``masks`` narrowed (flux, frames and images untouched; frames
        with fewer than 100 pixels trusted by both are left as they are).

    Raises:
        ValueError: if ``merged`` and ``views`` differ in shape.
    """
    import cv2

    if merged.flux.shape != views.flux.shape:
        raise ValueError(f"mask_disagreement: merged frames {merged.flux.shape} and views {views.flux.shape} "
                         "differ in shape")
    masks = merged.masks.copy()
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    opening = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (min_width_px, min_width_px))
    for i in range(len(masks)):
        a, b = merged.flux[i], views.flux[i]
        both = merged.masks[i] & views.masks[i] & np.isfinite(a) & np.isfinite(b)
        if np.count_nonzero(both) < 100:
            continue
        b = b * (float(np.median(a[both])) / max(float(np.median(b[both])), 1e-30))
        a, b = _noise_even(a, merged.exposure_s), _noise_even(b, merged.exposure_s)
        difference = np.abs(cv2.GaussianBlur(np.where(both, a - b, 0).astype(np.float32), (0, 0), smooth_px))
        spread = 1.4826 * float(np.median(difference[both])) + 1e-30
        found = cv2.morphologyEx((difference > sigmas * spread).astype(np.uint8), cv2.MORPH_OPEN, opening)
        if found.any():  # grown into the weaker test's regions that hold a candidate
            count, labels = cv2.connectedComponents((difference > grow_sigmas * spread).astype(np.uint8),
                                                    connectivity=8)
            grown = np.zeros(count, bool)
            grown[labels[found > 0]] = True
            grown[0] = False
            found = grown[labels].astype(np.uint8)
        masks[i] &= cv2.dilate(found, kernel) == 0
    return MergedFrames(merged.flux, merged.frames, merged.images, masks, merged.ids, merged.exposure_s)
