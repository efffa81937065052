"""The pairwise scheme's check of its registrations on binned frames, and their rescue.

Features need texture that a merged frame of a few photons per pixel does not show;
the scene's *signal* is still there, spread over many pixels. With ``group_size: auto``
the pairwise scheme hands every locator call's result to a :class:`PairCheck` (its
binning is the photon budget's ``check_binning``, :class:`~photonpano.budget.Budget`):

1. every pair the locator registered is **checked** on spatially binned merged frames
   (blocks of ``binning`` pixels, square-root flux, which makes photon noise about
   uniform; :func:`~photonpano.imaging.binned_frame`): the correlation of frame a with
   frame b warped by the homography must reach ``min_correlation``, else the pair
   counts as failed (a spurious match on photon noise correlates near 0);
2. every failed pair is registered **directly** on the binned frames: phase
   correlation for the translation left by the current estimate, then ECC
   (Evangelidis and Psarakis, 2008) for an affine correction of the estimate, and the
   same for a translation of the estimate's shift alone, whichever correlates better
   (:func:`~photonpano.imaging.register_binned`);
3. with ``mover_guard`` (the default), a single bright compact region (a lit object
   crossing a dark scene) must not decide a pair: each binned frame's
   :func:`~photonpano.movers.brightest_blob` is left out and the pair registered again
   (ECC from the phase correlation and from the current estimate); a registration of
   steps 1-2 is vetoed where the frames without their blobs correlate under it by more
   than ``guard_margin`` less than under their own registration, that one is nearer
   the current estimate (the chain's prediction) and the whole frames correlate less
   under it (the blobs move otherwise than the rest), and the pair takes theirs. A static
   scene's bright region leaves a rest that agrees, or registers further from the
   estimate: nothing is vetoed (docs/real_scenes.md, "Moving objects"). A pair that
   needs rescuing (step 2) takes the registration without the blobs where that
   correlates better than the whole frames under their own by ``rescue_margin``: a
   mover lowers the whole frames' correlation, too flat around the truth for the veto's
   margin (a disc crossing the brick facade pulled a rescue 3.3 px off at 0.727, against
   0.724 at the truth; without its blob 0.993, and 0.987 under the pulled registration).
   A static blob leaves the two within the margin: the low-texture clock's frames
   correlate at 0.99 over registrations pixels apart (under a 100 Hz lamp 0.210 -> 0.306 px
   with no margin, 0.252 at 0.05; the facade crossed by the disc 0.039 and 0.034 px).
4. at the level's end its rescues are **decided together** (:meth:`LevelCheck.settle`):
   one pair cannot tell whether the affine correction it chose follows the camera or a
   direction its frames do not pin (a checkerboard's rows leave the vertical scale free:
   after level 1 its vertical scale ramped by +-2.7 px at the frame's corners), but the
   level's rescues can. Where they scale one axis alone and do not turn (:func:`rescue_motion`),
   every rescue that both ECCs registered takes its translation (the checkerboard 0.540 ->
   0.075 px; ``docs/accuracy.md``, "Rescues decided together"). Before that: where homography
   ECCs refining the rescues (:func:`~photonpano.imaging.refine_binned_homography`; a sample
   first) add a steady keystone whose median reaches :data:`KEYSTONE_PX`, the camera turns out
   of the image plane (a tripod pan: affine rescues lost 24-44 px), and rescues take them.

A level's figures (correlation per pair, pairs checked out and rescued) travel in its
:attr:`~photonpano.records.LocateResult.check` to ``run.json``'s ``registration_check``.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import geometry
from ..executor import Executor, SerialExecutor
from ..imaging import (
    binned_frame,
    refine_binned_homography,
    register_binned,
    register_binned_motions,
    warped_correlation,
)
from ..movers import brightest_blob
from ..records import MergedFrames, PairRegistrations
from .keystone import KEYSTONE_PX, SIGNAL_LAG1, SIGNAL_T, keystones, rescue_motion, steady_keystone

__all__ = ["PairCheck", "LevelCheck", "rescue_motion", "SETTLE_MIN_RESCUES", "SIGNAL_LAG1", "SIGNAL_T", "KEYSTONE_PX"]


SETTLE_MIN_RESCUES = 10
"""Rescues (with both ECC registrations) a level needs before they are decided together;
with fewer, each keeps its own better registration."""
REFINE_SAMPLE = 4
"""One in this many rescues is refined first, to see whether the level can turn (:meth:`LevelCheck._refinements`)."""
REFINE_SAMPLE_MIN = 50
"""Passing sampled refinements needed to rule a turn out (fewer: every rescue is refined)."""
KEYSTONE_RULED_OUT_PX = 0.7
"""Median keystone (pixels at the frame's corner) of the sampled refinements under which the
level's cannot reach :data:`KEYSTONE_PX`: the others are not refined (docs/performance.md)."""


def _inliers(cc: float) -> int:
    """A rescue's pose-graph weight from its binned correlation: ``max(8, 100 cc^2)``."""
    return max(8, int(round(100 * cc ** 2)))


def _passing_keystones(refinements: Iterable[tuple[NDArray[np.float64], Any]]) -> NDArray[np.float64]:
    """(R, 2) float64 the keystones (pixels at the frame's corner) of the refinements that pass the check."""
    return np.array([tilt for tilt, refinement in refinements if refinement is not None]).reshape(-1, 2)


def _shape(affine: NDArray[np.float64], initial: NDArray[np.float64], radius: float) -> NDArray[np.float64]:
    """(4,) float64 rotation, zoom, anisotropy, shear of ``affine``'s correction of ``initial``, pixels at ``radius``.

    The correction ``affine @ inv(initial)`` is the ECC's affine warp (full-resolution
    pixels); of its linear part ``M``: rotation ``(M10 - M01) / 2``, zoom
    ``(M00 + M11) / 2 - 1``, anisotropy ``(M11 - M00) / 2`` (the vertical scale's excess
    over the horizontal one, halved), shear ``(M01 + M10) / 2``, each times ``radius``.
    """
    d = affine @ np.linalg.inv(initial)
    m = d[:2, :2] / d[2, 2]
    return radius * np.array([(m[1, 0] - m[0, 1]) / 2, (m[0, 0] + m[1, 1]) / 2 - 1, (m[1, 1] - m[0, 0]) / 2,
                              (m[0, 1] + m[1, 0]) / 2])


class PairCheck:
    """How the pairwise scheme checks and rescues its registrations (see the module).

    Args:
        binning: merged-frame pixels per side of the binned frames (>= 1).
        min_correlation: the binned correlation a registration must reach.
        min_overlap: fraction of binned pixels both frames must share.
        mover_guard: register every pair without each frame's brightest blob too, and
            prefer that registration where the frames without their blobs correlate
            better under it by more than ``guard_margin`` (see the module).
        guard_margin: the correlation margin of ``mover_guard``.
        rescue_margin: a rescue (step 2) takes the registration without the blobs where
            it correlates better than the whole frames' own by this much (see the module).
    """

    def __init__(self, binning: int, *, min_correlation: float = 0.4, min_overlap: float = 0.3,
                 mover_guard: bool = True, guard_margin: float = 0.2, rescue_margin: float = 0.05) -> None:
        """Set the check's binning and limits."""
        self.factor = max(1, int(binning))
        self.mover_guard, self.guard_margin, self.rescue_margin = mover_guard, guard_margin, rescue_margin
        self.min_correlation, self.min_overlap = min_correlation, min_overlap

    def start_level(self, executor: Executor) -> LevelCheck:
        """The check of one level: its binned frames and figures, run on ``executor``'s threads.

        A Dask executor's tasks would ship the frames to other processes, so with an
        executor outside this process the check runs here, one pair after another.
        """
        return LevelCheck(self, executor if executor.in_process else SerialExecutor())


def _binned_with_blob(flux: NDArray[np.float32], mask: NDArray[np.bool_], factor: int, find_blob: bool = True
                      ) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.bool_]]:
    """A merged frame's binned image, valid pixels and bright blob.

    The blob is :func:`~photonpano.movers.brightest_blob`'s, or none without ``find_blob`` (no mover guard).
    """
    image, valid = binned_frame(flux, mask, factor)
    return image, valid, brightest_blob(image, valid) if find_blob else np.zeros_like(valid)


class LevelCheck:
    """One level's :class:`PairCheck`: the binned frames kept across calls and the figures so far.

    Args:
        policy: the :class:`PairCheck`.
        executor: runs the binning and the pairs' checks (OpenCV and the compiled
            correlation release the GIL).
    """

    def __init__(self, policy: PairCheck, executor: Executor) -> None:
        """Start a level with no binned frames and no figures."""
        self.policy, self.executor = policy, executor
        self.checked = self.rejected = self.rescued = 0
        self.correlations: list[float] = []
        self._binned: dict[tuple[bytes, bytes], tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.bool_]]] = {}
        # per call, each rescue both ECCs registered: (pair in the call, index in correlations, (affine shape,
        # translation or None unless it passes, the homography refinement to run: see _refinements))
        self._alternatives: list[list[tuple[int, int, Any]]] = []
        self.rescue_motion: str | None = None
        self.rescue_shapes: dict[str, dict[str, float | bool]] | None = None
        self.pair_perspective: dict[str, Any] | None = None  # set by pairwise.drop_unsteady_perspective
        self.turning_camera: dict[str, Any] | None = None  # set by turning_camera.turning_keyframes

    @property
    def turns(self) -> bool:
        """Whether the level's camera turns out of the image plane, as on a tripod.

        True where its rescues decided ``"perspective"`` (:meth:`settle`) or its registered
        pairs' keystones are steady (:func:`~photonpano.schemes.pairwise.drop_unsteady_perspective`'s
        ``steady``): a keystone of 1 px or more at the corners that carries a signal.
        """
        return self.rescue_motion == "perspective" or bool((self.pair_perspective or {}).get("steady"))

    def settle(self, found: list[PairRegistrations]) -> list[PairRegistrations]:
        """Decide the level's rescues together, once every pair is registered (step 4 of the module).

        With at least :data:`SETTLE_MIN_RESCUES` rescues that both ECCs registered: where
        the keystones their homography refinements add carry a signal (lag-1
        autocorrelation >= :data:`SIGNAL_LAG1` or mean :data:`SIGNAL_T` standard errors
        from zero) with a median of :data:`KEYSTONE_PX` or more, every rescue takes its
        refinement where that passes the check (``"perspective"``); else, where their
        affine corrections scale one axis alone and do not turn (:func:`rescue_motion`),
        every such rescue takes its translation where that passes the check too.

        Args:
            found: the registrations this level's calls returned, in call order (each
                the (P) registrations of that call's pairs).

        Returns:
            The same list, the rescues revised where the level's decision is ``"perspective"``
            or ``"translation"``.
        """
        rows = [alternative for call in self._alternatives for _, _, alternative in call]
        if len(rows) < SETTLE_MIN_RESCUES:
            return found
        refined = self._refinements(rows)
        tilted = _passing_keystones(refined)
        tilts, turns = steady_keystone(tilted) if len(tilted) >= SETTLE_MIN_RESCUES else ({}, False)
        if turns:
            self.rescue_motion, self.rescue_shapes = "perspective", tilts
            taken = iter([refinement for _, refinement in refined])
        else:
            self.rescue_motion, self.rescue_shapes = rescue_motion(np.array([row[0] for row in rows]))
            if self.rescue_motion != "translation":
                return found
            taken = iter([row[1] for row in rows])
        revised = []
        for part, call in zip(found, self._alternatives):
            homographies, inliers, ok = part.homographies.copy(), part.inliers.copy(), part.ok.copy()
            for p, index, _ in call:
                registration = next(taken)
                if registration is not None:
                    homographies[p], inliers[p], ok[p] = registration[0], _inliers(registration[1]), True
                    self.correlations[index] = registration[1]
            revised.append(PairRegistrations(homographies, part.matches, inliers, ok))
        return revised

    def _refinements(self, rows: list[Any]) -> list[tuple[NDArray[np.float64], Any]]:
        """Each rescue's homography refinement ``(keystones, refinement)``, or [] where a sample rules a turn out.

        A refinement is one homography ECC per rescue (a third of level 1's time on the
        clock's 100 000 frames) and counts only where the level turns. Every
        :data:`REFINE_SAMPLE`-th rescue is refined first; where at least
        :data:`REFINE_SAMPLE_MIN` of those pass with a median keystone under
        :data:`KEYSTONE_RULED_OUT_PX` on both axes, the others are not refined.

        Args:
            rows: the level's rescue alternatives ``(shape, translation, refine)``, in registration order.

        Returns:
            One ``(keystones, refinement)`` per row, in order: (2,) float64 pixels at the
            frame's corner, and the refinement's ``(homography, correlation, overlap)``
            where it passes the check, else None; or [] (no turn).
        """
        sample = range(0, len(rows), REFINE_SAMPLE)
        done = dict(zip(sample, self.executor.map(lambda i: rows[i][2](), sample)))
        tilted = _passing_keystones(done.values())
        if len(tilted) >= REFINE_SAMPLE_MIN and np.median(np.abs(tilted), axis=0).max() < KEYSTONE_RULED_OUT_PX:
            return []
        rest = [i for i in range(len(rows)) if i not in done]
        done.update(zip(rest, self.executor.map(lambda i: rows[i][2](), rest)))
        return [done[i] for i in range(len(rows))]

    def __call__(self, merged: MergedFrames, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                 found: PairRegistrations) -> PairRegistrations:
        """Check, and rescue where they failed, a locator's registrations of ``pairs``.

        Each frame is binned once per content (:meth:`~photonpano.records.MergedFrames.content_key`):
        frames that the previous call used are reused, others are dropped.

        Args:
            merged: the merged frames the pairs index.
            pairs: (P, 2) int64 indices ``(a, b)`` into ``merged``.
            initial: (P, 3, 3) float64 current estimates mapping b's pixels to a's.
            found: the locator's (P) registrations of ``pairs``.

        Returns:
            The (P) registrations after the check: rescued pairs carry the direct
            registration (``inliers`` ``max(8, 100 cc^2)``), pairs that fail both are not ok.
        """
        factor = self.policy.factor
        frames = [int(i) for i in np.unique(pairs)]
        # a binned frame reads the flux and the mask: key both (one id when the frames carry ids)
        keys = {i: (merged.content_key(i), merged.content_key(i, flux=True)) for i in frames}
        missing = [i for i in frames if keys[i] not in self._binned]
        computed = dict(zip(missing, self.executor.map(
            lambda i: _binned_with_blob(merged.flux[i], merged.masks[i], factor, self.policy.mover_guard), missing)))
        binned = {i: computed[i] if i in computed else self._binned[keys[i]] for i in frames}
        self._binned = {keys[i]: binned[i] for i in frames}
        policy = self.policy

        def as_rescue(h: NDArray[np.float64], cc: float, alternative: Any = None
                      ) -> tuple[NDArray[np.float64], int, bool, float, bool, Any]:
            """A direct registration as a rescued pair (its inliers ``max(8, 100 cc^2)``, a pose-graph weight)."""
            return h, _inliers(cc), True, cc, True, alternative

        def check(p: int) -> tuple[NDArray[np.float64], int, bool, float, bool, Any]:
            """Pair p's (homography, inliers, ok, correlation, rescued, alternative)."""
            (a, a_valid, a_blob), (b, b_valid, b_blob) = binned[int(pairs[p, 0])], binned[int(pairs[p, 1])]
            whole, rest = ((a, a_valid), (b, b_valid)), ((a, a_valid & ~a_blob), (b, b_valid & ~b_blob))
            need = policy.min_overlap * max(int(b_valid.sum()), 1)

            @functools.cache
            def registered_without() -> tuple[NDArray[np.float64], float, bool]:
                """The frames registered without their blobs (once): (homography, correlation, ok)."""
                h, cc, overlap = register_binned(*rest, initial[p], factor, from_initial=True)
                enough = policy.min_overlap * max(int(rest[1][1].sum()), 1)
                return h, cc, cc >= policy.min_correlation and overlap >= enough

            corners = geometry.corners(a.shape[1] * factor, a.shape[0] * factor)
            vetoed: list[bool] = []

            def off(h: NDArray[np.float64]) -> float:
                """How far ``h`` moves the frame's corners from the current estimate's, in pixels."""
                return float(np.abs(geometry.apply(h, corners) - geometry.apply(initial[p], corners)).max())

            def holds(h: NDArray[np.float64], cc: float, overlap: int) -> bool:
                """The correlation and overlap pass, and the guard does not prefer the frames without blobs."""
                if not (cc >= policy.min_correlation and overlap >= need):
                    return False
                if not policy.mover_guard or not (a_blob.any() or b_blob.any()):
                    return True  # without blobs the frames' own registration cannot correlate worse whole
                rest_cc = warped_correlation(*rest, h, factor)[0]
                if rest_cc >= 1 - policy.guard_margin:  # no registration can beat it by the margin
                    return True
                other, best, ok = registered_without()
                veto = (ok and rest_cc < best - policy.guard_margin
                        and off(other) < off(h) and warped_correlation(*whole, other, factor)[0] < cc)
                vetoed.append(veto)
                return not veto

            homography, inliers = found.homographies[p], int(found.inliers[p])
            if found.ok[p]:
                cc, overlap = warped_correlation(*whole, homography, factor)
                if holds(homography, cc, overlap):
                    return homography, inliers, True, cc, False, None
            motions = register_binned_motions(*whole, initial[p], factor)
            h, cc, overlap = max(motions.values(), key=lambda motion: motion[1])
            if policy.mover_guard and (a_blob.any() or b_blob.any()) and cc + policy.rescue_margin <= 1:
                other, best, ok = registered_without()  # (a correlation above 1 - margin cannot be beaten)
                if ok and best >= cc + policy.rescue_margin:  # the blobs lowered the correlation: they moved
                    return as_rescue(other, best)
            if holds(h, cc, overlap):
                affine, translation = motions["affine"], motions["translation"]
                alternative = None
                if affine[1] > -1 and translation[1] > -1:  # both ECCs registered: for settle()
                    passes = translation[0] is h or holds(*translation)

                    def refine() -> tuple[NDArray[np.float64], Any]:
                        """The homography refinement's keystones and the refinement where it passes."""
                        perspective = refine_binned_homography(*whole, affine[0], factor)
                        return (keystones(perspective[0], affine[0], a.shape[1] * factor, a.shape[0] * factor),
                                perspective if perspective[1] > -1 and holds(*perspective) else None)

                    alternative = (_shape(affine[0], initial[p], (a.shape[1] * factor - 1) / 2),
                                   translation if passes else None, refine)
                return as_rescue(h, cc, alternative)
            if any(vetoed):  # a registration the frames without their blobs disagree with: theirs
                h, cc, _ = registered_without()
                return as_rescue(h, cc)
            return homography, inliers, False, cc, False, None

        checked = self.executor.map(check, range(len(pairs)))
        if not checked:
            return found
        ok = np.array([c[2] for c in checked], bool)
        rescued = np.array([c[4] for c in checked], bool)
        self.checked += int(found.ok.sum())
        self.rejected += int((found.ok & ~(ok & ~rescued)).sum())
        self.rescued += int(rescued.sum())
        self._alternatives.append([(p, len(self.correlations) + p, c[5]) for p, c in enumerate(checked)
                                   if c[5] is not None])
        self.correlations.extend(c[3] for c in checked)
        return PairRegistrations(np.stack([c[0] for c in checked]), found.matches,
                                 np.array([c[1] for c in checked], found.inliers.dtype), ok)

    def figures(self) -> dict[str, Any]:
        """The level's figures, JSON-ready (``run.json``'s ``registration_check``).

        Returns:
            ``{"binning", "checked", "rejected_by_check", "rescued",
            "median_correlation", "min_correlation", "rescue_motion", "rescue_shapes"}``
            (correlations of the pairs' final homographies on binned frames; -1 where ECC
            failed; None without pairs), and :meth:`settle`'s decision (``"perspective"``,
            ``"translation"`` or ``"per pair"``) and its figures: the keystones' ``{"horizontal",
            "vertical"}`` (each also with ``median_px``) for ``"perspective"``, else
            :func:`rescue_motion`'s (None where the rescues were too few to decide); and
            ``"pair_perspective"``, :func:`~photonpano.schemes.pairwise.drop_unsteady_perspective`'s;
            ``"turning_camera"``, :func:`~photonpano.turning_camera.turning_keyframes`'s where the
            level :attr:`turns`, else None.
        """
        cc = np.asarray(self.correlations, np.float64)
        return {"binning": self.policy.factor, "checked": self.checked, "rejected_by_check": self.rejected,
                "rescued": self.rescued, "median_correlation": float(np.median(cc)) if len(cc) else None,
                "min_correlation": float(cc.min()) if len(cc) else None,
                "rescue_motion": self.rescue_motion, "rescue_shapes": self.rescue_shapes,
                "pair_perspective": self.pair_perspective, "turning_camera": self.turning_camera}
