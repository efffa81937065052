"""The ``pairwise`` level scheme: pairs of merged frames, chained and solved as a pose graph.

The paper's locate step (Sec. 4): consecutive merged frames are registered and chained;
longer-offset pairs that the chain predicts to overlap are registered too and all pairs
are solved jointly (:mod:`photonpano.posegraph`), so that a wrong consecutive link is
outvoted. Merged frames stream through a ring (:func:`locate_keyframes`), so memory does
not grow with the capture. With the pair check, the few perspectives a locator gives by
chance are dropped (:func:`drop_unsteady_perspective`).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterator

import numpy as np
from numpy.typing import NDArray

from .. import geometry
from ..errors import StageError
from ..guards import plausible
from ..locator import Locator, LocatorContext
from ..posegraph import chain_keyframes, corner_disagreement, median_disagreement, pairs_at_offsets, refine_keyframes
from ..records import LocateResult, MergedFrames, PairRegistrations
from ..turning_camera import turning_keyframes
from ..watchdog import watched
from .base import LevelScheme, LevelTask
from .check import SETTLE_MIN_RESCUES, LevelCheck, PairCheck
from .keystone import keystones, steady_keystone

__all__ = ["PairwiseScheme", "locate_keyframes", "drop_unsteady_perspective", "CHANCE_PERSPECTIVE_SHARE"]


class _MergedRing:
    """Merged frames of the last ``capacity`` groups, group j in slot ``j % capacity``.

    Each put gives its slots new content ids (:attr:`MergedFrames.ids`), which name the
    frames to the locator: a call gets the frames its pairs use, in group order, and
    pairs of ids, so neither depends on the slots (and a locator's per-frame caches know
    a frame seen by an earlier call without digesting its pixels).
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.frames: MergedFrames | None = None

    def put(self, index: NDArray[np.int64], merged: MergedFrames) -> None:
        if self.frames is None:
            shape = (self.capacity,) + merged.flux.shape[1:]
            flux, frames, images, masks = (np.zeros(shape, getattr(merged, f).dtype)
                                           for f in ("flux", "frames", "images", "masks"))
            self.frames = MergedFrames(flux, frames, images, masks, ids=np.full(self.capacity, -1, np.int64),
                                       exposure_s=merged.exposure_s)
        slots = index % self.capacity
        for f in ("flux", "frames", "images", "masks"):
            getattr(self.frames, f)[slots] = getattr(merged, f)
        self.frames.ids[slots] = MergedFrames.new_ids(len(slots))

    def register(self, locator: Locator, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                 context: LocatorContext) -> tuple[MergedFrames, NDArray[np.int64], PairRegistrations]:
        """Register group pairs held in the ring.

        The locator gets the frames of the groups ``pairs`` use (group order) and the
        pairs as their frame ids (:meth:`Locator.register_pairs`).

        Args:
            locator: the built locator.
            pairs: (P, 2) int64 group indices, each group among the last ``capacity`` put.
            initial: (P, 3, 3) float64 starts (b's pixels to a's).
            context: how the locator's call may run.

        Returns:
            ``(frames, positions, found)``: the frames the locator got, the (P, 2) int64
            pairs as positions in them, and the locator's (P) registrations.
        """
        groups = np.unique(pairs)
        frames = self.frames.take(groups % self.capacity)
        found = locator.register_pairs(frames, frames.ids[np.searchsorted(groups, pairs)], initial, context)
        return frames, np.searchsorted(groups, pairs), found


def _overlapping(pairs: NDArray[np.int64], keyframes: NDArray[np.float64], width: int, height: int,
                 min_overlap: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Keep the pairs whose frames ``keyframes`` predict to overlap by ``min_overlap``; return them and their maps."""
    expected = np.linalg.inv(keyframes[pairs[:, 0]]) @ keyframes[pairs[:, 1]]
    centre = np.array([[(width - 1) / 2, (height - 1) / 2]])
    shift = geometry.apply(expected, centre)[:, 0] - centre
    overlap = np.clip(1 - np.abs(shift[:, 0]) / width, 0, 1) * np.clip(1 - np.abs(shift[:, 1]) / height, 0, 1)
    keep = overlap >= min_overlap
    return pairs[keep], expected[keep]


def _merged_windows(merge: Callable[[NDArray[np.int64]], MergedFrames], windows: list[NDArray[np.int64]],
                    ahead: bool) -> Iterator[MergedFrames]:
    """Yield ``merge(window)`` for each window; with ``ahead``, the next one merges on a helper thread meanwhile."""
    if not ahead:
        yield from (merge(index) for index in windows)
        return
    with ThreadPoolExecutor(1, thread_name_prefix="photonpano-merge-ahead") as helper:
        pending = helper.submit(merge, windows[0]) if windows else None
        for k in range(len(windows)):
            done, pending = pending, helper.submit(merge, windows[k + 1]) if k + 1 < len(windows) else None
            yield done.result()


def locate_keyframes(locator: Locator, merge: Callable[[NDArray[np.int64]], MergedFrames],
                     current: NDArray[np.float64], pair_offsets: tuple[int, ...], width: int, height: int, *,
                     window: int = 32, min_overlap: float = 0.5, outlier_px: float = 1.0, merge_ahead: bool = False,
                     check: LevelCheck | None = None, context: LocatorContext | None = None,
                     turning_camera: bool = True) -> tuple[NDArray[np.float64], NDArray[np.int64], PairRegistrations]:
    """Register merged frames pairwise and solve for the homographies of their reference frames.

    1. Consecutive pairs are registered and chained (:func:`chain_keyframes`), failed
       or implausible pairs bridged.
    2. For each offset k > 1, pairs ``(g - k, g)`` that the chain predicts to overlap by
       at least ``min_overlap`` are registered too.
    3. All plausible pairs are solved jointly (:func:`refine_keyframes`, robust loss);
       pairs whose corners disagree with that solution by more than
       ``max(outlier_px, 4 x median disagreement)`` are rejected and the graph is
       solved again. A wrong consecutive link is thereby outvoted by the longer pairs
       spanning it.
    4. With ``turning_camera`` and a ``check`` that finds the level's camera turning
       (:attr:`~photonpano.schemes.check.LevelCheck.turns`), the graph is solved again as a
       camera turning about its centre (:func:`~photonpano.turning_camera.turning_keyframes`),
       kept where it agrees with the pairs nearly as well.

    Merged frames stream: ``merge`` is called on consecutive windows of ``window``
    groups and steps 1 and 2 run as they arrive (one ``register_pairs`` call per
    window), keeping only the merged frames that later pairs reach back to. Memory is
    thus bounded by ``3 x window + max(pair_offsets)`` merged frames whatever the
    capture length; the pose graph (step 3) holds only the pair homographies.

    Args:
        locator: the built locator.
        merge: ``merge(index)`` returns the merged frames of groups ``index`` ((K,)
            int64, consecutive and increasing).
        current: (G, 3, 3) float64 current homographies of the reference frames.
        pair_offsets: offsets k (1 is always used).
        width: frame width in pixels.
        height: frame height in pixels.
        window: groups merged and registered at a time.
        min_overlap: predicted overlap (fraction of the frame) needed to try a pair.
        outlier_px: smallest rejection threshold, in pixels (corner distance).
        merge_ahead: merge each next window on a helper thread while this one registers
            (``merge`` must then be callable from another thread). With a thread pool
            behind both, its workers stay busy across each window's last tasks.
        context: how the locator's calls may run (its executor; None: serially).
        check: checks (and rescues) every locator call's registrations, then settles the
            level's rescues together (:class:`~photonpano.schemes.check.LevelCheck`), or None.
        turning_camera: step 4 (the spec's ``camera_model: auto``).

    Returns:
        ``(keyframes, pair_index, pairs)``: (G, 3, 3) float64 homographies, (P, 2)
        int64 pairs tried (the G - 1 consecutive pairs first) and their registrations
        (``ok`` False where failed or rejected).

    Raises:
        StageError: if every consecutive pair failed.
    """
    g = len(current)
    offsets = tuple(k for k in sorted(set(pair_offsets)) if 1 < k < g)
    windows = [np.arange(s, min(s + window, g)) for s in range(0, g, window)]
    ring = _MergedRing(min(g, 2 * window + max(offsets, default=0)))
    predicted = np.linalg.inv(current[:-1]) @ current[1:]
    chain_parts: list[PairRegistrations] = []
    calls: list[tuple[NDArray[np.int64], int, PairRegistrations]] = []  # (pairs, consecutive ones, found)
    # One locator call per window: its consecutive pairs, and the longer pairs ending in the
    # previous window, whose overlap the chain up to there predicts. A frame is thus used
    # by consecutive calls only, and a locator's per-call cache describes it once.
    merged = _merged_windows(merge, windows, merge_ahead)

    def sane(found: PairRegistrations) -> PairRegistrations:
        """``found`` with its implausible registrations counted as failed."""
        return found.with_ok(found.ok & plausible(found.homographies, width, height))

    for w in range(len(windows) + 1):
        index, initial = [np.zeros((0, 2), np.int64)], [np.zeros((0, 3, 3))]
        if w < len(windows):
            new = windows[w]
            ring.put(new, next(merged))
            index.append(np.stack([new - 1, new], axis=1)[new > 0])
            initial.append(predicted[index[-1][:, 0]])
        n_chain = len(index[-1])
        if offsets and w > 0:
            done = windows[w - 1]
            chained = PairRegistrations.concat(*chain_parts)
            try:
                so_far = chain_keyframes(current[:done[-1] + 1], chained)
            except StageError:  # every consecutive pair so far failed
                so_far = current[:done[-1] + 1]
            reach = np.concatenate([np.stack([done - k, done], axis=1)[done >= k] for k in offsets])
            reach, expected = _overlapping(reach, so_far, width, height, min_overlap)
            index.append(reach)
            initial.append(expected)
        index_all = np.concatenate(index)
        if not len(index_all):
            continue
        starts = np.concatenate(initial)
        frames, positions, found = ring.register(locator, index_all, starts, context or LocatorContext())
        if check is not None:
            found = check(frames, positions, starts, found)
        found = sane(found)
        calls.append((index_all, n_chain, found))
        chain_parts.append(found.take(slice(0, n_chain)))
    founds = [found for _, _, found in calls]
    if check is not None and calls:  # the level's rescues decided together
        founds = [sane(f) for f in check.settle(founds)]
        if check.rescue_motion != "perspective":  # (a level whose rescues turn keeps every perspective)
            founds, check.pair_perspective = drop_unsteady_perspective(founds, width, height)
    chain_parts = [f.take(slice(0, n)) for (_, n, _), f in zip(calls, founds)]
    extra_parts = [(i[n:], f.take(slice(n, None))) for (i, n, _), f in zip(calls, founds) if len(i) > n]
    chain_index = pairs_at_offsets(g, (1,))
    chain = PairRegistrations.concat(*chain_parts)
    keyframes = chain_keyframes(current, chain)
    if not extra_parts:
        return keyframes, chain_index, chain
    extra = np.concatenate([index for index, _ in extra_parts])
    found = PairRegistrations.concat(*(found for _, found in extra_parts))
    pair_index = np.concatenate([chain_index, extra])
    # Bridged consecutive pairs enter the solve with a token weight (one inlier) so
    # that the pose graph stays connected across registration failures.
    steps = np.linalg.inv(keyframes[:-1]) @ keyframes[1:]
    bridged = PairRegistrations(steps, chain.matches, np.where(chain.ok, chain.inliers, 1),
                                np.ones(len(steps), bool))
    graph = PairRegistrations.concat(bridged, found)
    solved = refine_keyframes(keyframes, pair_index, graph, width, height)
    # A wrong registration that looked plausible disagrees with the joint solution of
    # all the others: drop such pairs and solve again.
    measured = PairRegistrations.concat(chain, found).ok
    residual = corner_disagreement(graph.homographies,
                                    np.linalg.inv(solved[pair_index[:, 0]]) @ solved[pair_index[:, 1]], width, height)
    limit = max(outlier_px, 4 * float(np.median(residual[measured]))) if measured.any() else np.inf
    outliers = measured & (residual > limit)
    if outliers.any():
        graph = graph.with_ok(graph.ok & ~outliers)
        solved = refine_keyframes(solved, pair_index, graph, width, height)
    pairs = PairRegistrations.concat(chain, found)
    pairs = pairs.with_ok(pairs.ok & ~outliers)
    # Safety net: a joint solve that agrees with the trusted pairs worse than the chain
    # does (it did not converge) is discarded for the chain.
    trusted = pairs.ok
    if trusted.any():
        def disagreement(k: NDArray[np.float64]) -> float:
            return median_disagreement(k, pair_index, graph, trusted, width, height)

        if not np.isfinite(disagreement(solved)) or disagreement(solved) > disagreement(keyframes):
            solved = keyframes
        if turning_camera and check is not None and check.turns:
            solved, check.turning_camera = turning_keyframes(solved, pair_index, graph, trusted, width, height)
    return solved, pair_index, pairs


CHANCE_PERSPECTIVE_SHARE = 0.25
"""Share of a level's registered pairs below which the perspectives its locator gave are taken
for chance (:func:`drop_unsteady_perspective`): 0.9-4.6 % on the fast pans that halt where they
bent the trajectory, 15 % on dandelions shaken by a turning camera (its perspective at level 1
neither helps nor hurts), 53 % on the city shaken so, 84 % on a tripod pan."""


def drop_unsteady_perspective(found: list[PairRegistrations], width: int, height: int
                              ) -> tuple[list[PairRegistrations], dict[str, Any] | None]:
    """A level's pair registrations as affine maps where the few perspectives among them are chance.

    A locator that chooses each pair's model (``opencv-sift``'s ``motion: auto``, the
    lowest GRIC) now and then gives a pair a homography whose perspective (``p7, p8``) is
    noise. Chained along the capture, a handful of them bend it: a keystone and scale that
    wander by a pixel at the frame's corners, which the mosaic levels' template then holds
    (a 0.06 px/frame pan that halts every 6 000 frames over the handwriting: 5 of 549
    pairs, 0.254 px, ``ok`` with a median sigma of 0.077; made affine, 0.067 px). A camera
    that turns gives most pairs a perspective (a shaking turn, a tripod pan), and a tripod
    pan needs it at level 1 (the mosaic levels cannot undo the 24-44 px an affine level 1
    leaves there). So where fewer than :data:`CHANCE_PERSPECTIVE_SHARE` of the registered
    pairs have a perspective, and those do not add a steady keystone (at least
    :data:`~photonpano.schemes.check.SETTLE_MIN_RESCUES` of them, whose keystones carry a
    signal with a median of :data:`~photonpano.schemes.keystone.KEYSTONE_PX` or more pixels
    at the corner, :func:`~photonpano.schemes.keystone.steady_keystone`, as
    :meth:`~photonpano.schemes.check.LevelCheck.settle` asks of the rescues), each
    registered pair with a perspective takes the affine map closest to its homography
    (least squares at a 4 x 4 grid of frame pixels); the first mosaic level registers what
    perspective there is.

    Args:
        found: the level's registrations, per locator call (after the check's settle).
        width: merged frame width in pixels.
        height: merged frame height in pixels.

    Returns:
        ``(found, figures)``: the registrations (the same objects where the perspective is
        kept) and ``{"kept", "steady", "pairs", "with_perspective", "horizontal", "vertical"}`` (the
        keystones' ``{"lag1", "t", "signal", "median_px"}`` over the pairs with a
        perspective, None for fewer than ``SETTLE_MIN_RESCUES``); None for fewer than
        ``SETTLE_MIN_RESCUES`` registered pairs.
    """
    ok = np.concatenate([part.ok for part in found])
    registered = np.concatenate([part.homographies for part in found])[ok]
    if len(registered) < SETTLE_MIN_RESCUES:
        return found, None
    tilted = keystones(registered[_given_perspective(registered)], np.eye(3), width, height)  # pixels at the corner
    tilts: dict[str, Any] = {"horizontal": None, "vertical": None}
    steady = False
    if len(tilted) >= SETTLE_MIN_RESCUES:
        tilts, steady = steady_keystone(tilted)
    kept = len(tilted) >= CHANCE_PERSPECTIVE_SHARE * len(registered) or steady
    figures = {"kept": kept, "steady": steady, "pairs": len(registered), "with_perspective": len(tilted), **tilts}
    if kept or not len(tilted):
        return found, figures
    grid = geometry.pixel_grid(width, height, 4)
    fit = np.linalg.pinv(np.column_stack([grid, np.ones(len(grid))]))  # (3, 16): least squares onto x, y, 1
    flattened = []
    for part in found:
        affine = np.zeros_like(part.homographies)
        affine[:, :2] = np.einsum("ij,pjk->pki", fit, geometry.apply(part.homographies, grid))
        affine[:, 2, 2] = 1
        given = part.ok & _given_perspective(part.homographies)
        flattened.append(PairRegistrations(np.where(given[:, None, None], affine, part.homographies),
                                           part.matches, part.inliers, part.ok))
    return flattened, figures


def _given_perspective(homographies: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(P,) bool the registrations (P, 3, 3) whose locator gave them a perspective (``p7`` or ``p8`` not zero)."""
    return np.abs(homographies[:, 2, :2]).max(axis=1) > 0


class PairwiseScheme(LevelScheme):
    """Register pairs of merged frames and solve the pose graph (the paper's scheme).

    Args:
        locator: the built locator (its calls get the task's executor for their per-pair
            work, :class:`~photonpano.locator.LocatorContext`).
        pair_offsets: register merged frames g and g + k for each k (1 is always used).
        check: the binned check of every registration (:class:`~photonpano.schemes.check.PairCheck`;
            the photon budget's ``check_binning``), or None; its figures are the
            result's :attr:`~photonpano.records.LocateResult.check`.
        advice: appended to the error of a level at which no pair registered (what the
            user can change, e.g. that an explicit group size left the check off).
        turning_camera: solve a level whose camera turns as a camera turning about its
            centre (:func:`locate_keyframes`' step 4; the spec's ``camera_model: auto``).
    """

    name = "pairwise"

    def __init__(self, locator: Locator, pair_offsets: tuple[int, ...] = (1,), check: PairCheck | None = None,
                 advice: str = "", *, turning_camera: bool = True) -> None:
        """Create the scheme around a built locator."""
        self.locator = locator
        self.turning_camera = turning_camera
        self.pair_offsets = tuple(pair_offsets)
        self.check = check
        self.advice = advice

    def locate(self, task: LevelTask) -> LocateResult:
        """Stream-merge the groups, register pairs, solve (see :func:`locate_keyframes`)."""
        kept: list[MergedFrames] = []
        merge_s = 0.0

        def merge(index: NDArray[np.int64]) -> MergedFrames:
            nonlocal merge_s
            start = time.perf_counter()
            with watched("merger", task.merger, "merge"):
                part = task.merger.merge(task.source, task.homographies, task.groups.select(index),
                                         progress=task.progress, executor=task.executor)
            merge_s += time.perf_counter() - start
            if task.keep_merged:
                kept.append(part)
            return part

        self.locator.reset_cache_stats()
        check = self.check.start_level(task.executor) if self.check is not None else None
        try:
            keyframes, pair_index, pairs = locate_keyframes(
                self.locator, merge, task.current, self.pair_offsets, task.source.width, task.source.height,
                merge_ahead=task.executor.in_process and task.executor.workers > 1, check=check,
                context=LocatorContext(executor=task.executor), turning_camera=self.turning_camera)
        except StageError as err:
            raise StageError("locator", type(self.locator).__name__,
                             f"level {task.level}: {err.reason}{self.advice}") from None
        finally:
            self.locator.end_level()
        return LocateResult(keyframes, pairs, pair_index, merged=MergedFrames.concat(*kept) if kept else None,
                            merge_s=merge_s, locator_cache=self.locator.cache_stats() or None,
                            check=check.figures() if check is not None else None)
