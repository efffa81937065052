"""The level loop of stratified temporal re-sampling (the paper's Sec. 4), top-down.

Each level: **re-sample** the capture into groups, let the level's scheme **merge** and
**locate** them (:mod:`photonpano.schemes`), **guard** the keyframe updates, and
**interpolate** the keyframe poses to every binary frame; then emit the level's
frozen :class:`~photonpano.records.LevelResult`.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from . import geometry, long_pairs
from .errors import StageError
from .executor import Executor, SerialExecutor
from .guards import guard_keyframes, plausible
from .information import SHAPE, conditional_shift
from .records import Groups, LevelResult
from .schemes import LevelScheme, LevelTask
from .stages import Interpolator, Merger, PhotonSource, Resampler
from .watchdog import watched

__all__ = ["estimate_motion"]


def estimate_motion(source: PhotonSource, resampler: Resampler, merger: Merger, interpolator: Interpolator,
                    schemes: Sequence[LevelScheme], *, group_size: int, executor: Executor | None = None,
                    keep_merged: bool = False, on_level: Callable[[LevelResult], None] | None = None,
                    progress: Callable[[str, int], Callable[[int], None]] | None = None, start_level: int = 1,
                    initial: NDArray[np.float64] | None = None, crosscheck: bool = True,
                    correct_shape_drift: bool = False,
                    revise: Callable[[LevelResult], Sequence[LevelScheme] | None] | None = None
                    ) -> NDArray[np.float64]:
    """Estimate a homography for every binary frame by stratified re-sampling.

    One level per scheme. Each level re-samples groups, has its scheme merge them with
    the current homographies (relative to each group's reference frame) and register
    them into keyframe homographies, and interpolates the keyframe poses (each standing
    for its group's mean pose, in panorama coordinates centred on the middle frame's
    centre, see :func:`_interpolate`) to every frame: the paper's interpolation of the
    keyframe homographies, at every level.

    Args:
        source: the capture.
        resampler: the built resampler (groups of each level).
        merger: the built merger (virtual exposures).
        interpolator: the built interpolator (homographies for every binary frame).
        schemes: the scheme of each level (its length is the number of levels); the
            first must not need an estimate (``pairwise``).
            Each distinct scheme is prepared once with the groups of every level to
            run (:meth:`~photonpano.schemes.LevelScheme.prepare`, timed with the first
            level's ``merge``) and closed at the end.
        group_size: binary frames per group m.
        executor: runs independent work (None: serially).
        keep_merged: keep each level's merged frames in its result (for dumps).
        on_level: called with each finished level.
        progress: ``progress(description, total)`` returns an ``advance(n)`` callable.
        start_level: resume with this level (the result equals that of an uninterrupted run).
        initial: (T, 3, 3) float64 homographies after level ``start_level - 1`` (that
            :class:`~photonpano.records.LevelResult`'s); None: identities.
        crosscheck: have the last level's scheme also register its consecutive merged
            frames against each other, held out of the fit (the evidence of
            :mod:`photonpano.uncertainty`), and chains of merged frames far apart
            (:mod:`photonpano.long_pairs`).
        correct_shape_drift: take the shape error those chains agree on out of the last
            level's trajectory (:func:`~photonpano.long_pairs.correct_shape_drift`; the
            level's ``timings_s`` then has ``shape_drift``, its result the trajectory before
            it and the largest move, :class:`~photonpano.records.LevelResult`).
        revise: called after ``on_level`` with each finished level; may return the schemes
            of every level (the same length) to change those of the levels after it
            (a scheme new to the run is prepared with their groups, and closed at the end),
            or None to keep them.

    Returns:
        (T, 3, 3) float64 frame-to-panorama homographies, where panorama coordinates are
        the pixel coordinates of the middle binary frame ``T // 2`` (its homography is
        the identity); each level's result is in the same coordinates.

    Raises:
        StageError: if a level cannot register anything, or its update is implausible.
        ValueError: if the first scheme needs an estimate.
    """
    n = source.n_frames
    homographies = np.repeat(np.eye(3)[None], n, axis=0) if initial is None else np.array(initial, np.float64)
    executor = executor or SerialExecutor()
    if start_level == 1 and schemes and schemes[0].needs_template:
        raise ValueError(f"level 1 cannot use the {schemes[0].name} scheme: it refines an existing estimate")
    distinct = list({id(scheme): scheme for scheme in schemes[start_level - 1:]}.values())
    try:
        resampled = {}  # each level's groups and the time it took to re-sample them
        for level in range(start_level, len(schemes) + 1):
            t0 = time.perf_counter()
            resampled[level] = _resample(resampler, n, group_size, level), time.perf_counter() - t0
        # the interpolator's first call may import libraries (scipy.interpolate: 0.17 s): load
        # them while the photons are counted (compiled, GIL-free) and level 1 runs
        threading.Thread(target=_warm_up, args=(interpolator,), name="photonpano-warm-up", daemon=True).start()
        t_prepare = time.perf_counter()
        for scheme in distinct:
            scheme.prepare([groups for groups, _ in resampled.values()], group_size, executor)
        prepare_s = time.perf_counter() - t_prepare  # merge work: reported with the first level's merge
        for level in range(start_level, len(schemes) + 1):
            scheme, (groups, resample_s) = schemes[level - 1], resampled[level]
            t1 = time.perf_counter()
            task = LevelTask(level, source, merger, groups, homographies, group_size, executor, keep_merged,
                             crosscheck=crosscheck and level == len(schemes),
                             progress=progress(f"level {level}: merge + locate", len(groups)) if progress else None)
            located = scheme.locate(task)
            t2 = time.perf_counter()
            current = homographies[groups.reference]
            keyframes, rejected = guard_keyframes(current, located.keyframes, source.width, source.height)
            updated = _interpolate(interpolator, groups, keyframes, homographies, source, level)
            if located.information is not None:  # each shift given the smoothed shape, then again
                keyframes = _condition_shifts(keyframes, updated[groups.reference], located.information, source)
                updated = _interpolate(interpolator, groups, keyframes, homographies, source, level)
            homographies = _gauge(updated)
            t3 = time.perf_counter()
            first = prepare_s if level == start_level else 0.0
            timings = {"resample": resample_s, "merge": located.merge_s + first, "locate": t2 - t1 - located.merge_s,
                       "interpolate": t3 - t2}
            uncorrected, drift = None, None
            if correct_shape_drift and located.chain is not None and located.chain_index is not None:
                uncorrected = homographies
                corrected, drift = long_pairs.correct_shape_drift(
                    located.chain.homographies, located.chain.ok, located.chain_index, groups.reference,
                    homographies, source.width, source.height)
                homographies = _gauge(corrected)
                timings["shape_drift"] = time.perf_counter() - t3
            result = LevelResult(level, scheme.name, groups, located, homographies, timings, rejected, uncorrected,
                                 drift)
            if on_level is not None:
                on_level(result)
            if revise is not None and (revised := revise(result)) is not None:
                schemes = list(schemes[:level]) + list(revised[level:])
                fresh = list({id(s): s for s in schemes[level:] if all(s is not d for d in distinct)}.values())
                for added in fresh:
                    added.prepare([resampled[later][0] for later in range(level + 1, len(schemes) + 1)],
                                  group_size, executor)
                distinct += fresh
        return homographies
    finally:
        for scheme in distinct:
            scheme.close()


def _warm_up(interpolator: Interpolator) -> None:
    """Run the interpolator's :meth:`~photonpano.stages.Interpolator.warm_up`, ignoring its errors."""
    try:
        getattr(interpolator, "warm_up", lambda: None)()
    except Exception:  # noqa: BLE001 - the first real call reports them
        pass


def _resample(resampler: Resampler, n: int, group_size: int, level: int) -> Groups:
    """The level's groups; a capture too short for them is the resampler's error."""
    try:
        with watched("resampler", resampler, "groups"):
            return resampler.groups(n, group_size, level)
    except ValueError as exc:
        raise StageError("resampler", type(resampler).__name__, str(exc)) from None


def _interpolate(interpolator: Interpolator, groups: Groups, keyframes: NDArray[np.float64],
                 homographies: NDArray[np.float64], source: PhotonSource, level: int) -> NDArray[np.float64]:
    """Interpolate the keyframe poses to every frame (refusing folds).

    The interpolator fits the *trajectory*, not a correction of it, so that its smoothness
    penalty acts on the camera's motion (a pan's shape is constant however noisy the
    level before was). Poses are taken in panorama coordinates with the origin moved to the
    middle frame's centre (``Z = inv(T_c) @ K @ T_c``, panorama coordinates being the
    middle frame's pixels): there ``p5, p6`` are the frame centre's position and
    ``p1..p4`` the frame's rotation, scale and shear wherever it is, so an interpolator
    may smooth them differently (``cubic-lk``'s ``shape_smoothness``).

    What a keyframe measures: its merged frame holds the group's frames warped to the
    reference frame by the current estimate, so the registration finds the reference
    frame's current pose moved by the *mean* over the group of the current estimate's
    error. Each keyframe is handed over as the group's mean pose, ``params(Z_g) -
    a(ref_g) + mean_(t in g) a(t)`` with ``a(t)`` the parameters of the current estimate
    (the exposure-average measurement of paper suppl. S.2; at level 1, where the estimate
    is the identity, this is the keyframe itself).
    """
    w, h = source.width, source.height
    trajectory = geometry.params_from_homographies(geometry.about_centre(homographies, w, h))
    cumulative = np.concatenate([np.zeros((1, 8)), np.cumsum(trajectory, axis=0)])
    mean = (cumulative[groups.stop] - cumulative[groups.start]) / (groups.stop - groups.start)[:, None]
    poses = (geometry.params_from_homographies(geometry.about_centre(keyframes, w, h))
             - trajectory[groups.reference] + mean)
    with watched("interpolator", interpolator, "interpolate"):
        fitted = interpolator.interpolate(groups.reference, geometry.homographies_from_params(poses),
                                          len(homographies), groups)
    updated = geometry.normalize(geometry.from_centre(fitted, w, h))
    update = geometry.invert(homographies) @ updated
    ok = plausible(update, w, h)
    if not ok.all():
        # a turning pan's frames far from the gauge frame are in perspective beyond the area
        # bound (level 1's update is the whole pose): what must hold is that each frame's
        # update agrees with that of the nearest reference frame, and that it folds nothing
        frames, ref = np.flatnonzero(~ok), groups.reference
        after = np.clip(np.searchsorted(ref, frames), 0, len(ref) - 1)
        before = np.maximum(after - 1, 0)
        nearest = np.where(np.abs(ref[before] - frames) <= np.abs(ref[after] - frames), ref[before], ref[after])
        ok[~ok] = plausible(geometry.invert(update[nearest]) @ update[~ok], w, h) & _unfolded(updated[~ok], w, h)
    if not ok.all():
        raise StageError("interpolator", type(interpolator).__name__,
                         f"level {level}: the interpolated update folds or rescales some frames")
    return updated


def _unfolded(homographies: NDArray[np.float64], width: int, height: int) -> NDArray[np.bool_]:
    """Whether each homography keeps the frame a convex quadrilateral of the same orientation (any area)."""
    return plausible(homographies, width, height, max_area_change=np.inf)


def _condition_shifts(keyframes: NDArray[np.float64], fitted: NDArray[np.float64], information: NDArray[np.float64],
                      source: PhotonSource) -> NDArray[np.float64]:
    """Move each keyframe's shift to where its registration puts it given the fitted shape.

    A registration's shift error is correlated with its shape error (the perspective
    terms move pixels by ``x^2``, whose mean over the frame is not zero); the interpolator
    smooths the shape over many keyframes, so each keyframe's shift is replaced by its
    maximum-likelihood value given the fitted shape (:func:`~photonpano.information.conditional_shift`).

    Args:
        keyframes: (G, 3, 3) float64 registered keyframe homographies (frame to panorama).
        fitted: (G, 3, 3) float64 the fitted trajectory at the keyframes' reference frames.
        information: (G, 8, 8) float64 each registration's information, parameters about
            the frame centre in sensor pixels (zero: left as is).
        source: the capture (its frame size).

    Returns:
        (G, 3, 3) float64 keyframes with corrected shifts.
    """
    w, h = source.width, source.height
    relative = geometry.about_centre(np.linalg.inv(fitted) @ keyframes, w, h)
    shape_error = geometry.params_from_homographies(relative)[:, SHAPE]
    shift = conditional_shift(information, shape_error)
    move = np.repeat(np.eye(3)[None], len(keyframes), axis=0)
    move[:, :2, 2] = shift
    return geometry.normalize(keyframes @ geometry.from_centre(move, w, h))


def _gauge(updated: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fix panorama coordinates to the middle frame's pixels.

    The panorama has the middle frame's scale and perspective (as a stitching reference
    image in the middle of the sequence keeps distortion low).
    """
    return geometry.normalize(np.linalg.inv(updated[len(updated) // 2]) @ updated)
