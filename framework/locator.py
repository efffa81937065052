"""The locator contract: registration of merged frames, with everything a call needs passed to it.

A locator estimates homographies between merged frames (the paper's *locate* step,
Sec. 4). The framework calls one of two public methods, which validate their inputs
and call the protected method a plugin implements (as a pytest plugin's hooks get
their arguments, and kornia's matchers take pre-extracted features as arguments,
nothing is injected as an attribute):

- :meth:`Locator.register_pairs`: pairs of merged frames of one level (the ``pairwise``
  scheme, and the held-out cross-check), each pair naming its two frames by id
  (:attr:`MergedFrames.ids <photonpano.records.MergedFrames>`), never by where a scheme
  buffers them -> :meth:`Locator._register_pairs`, which gets the frames the pairs name
  and their positions among these;
- :meth:`Locator.register_to_template`: each merged frame against the panorama
  rendered at its pose (the ``mosaic`` scheme) -> :meth:`Locator._register_to_template`,
  which by default registers the pairs (view g, frame g) of the two stacked.

How a call may run is a :class:`LocatorContext`: the executor for per-frame and per-pair
work, and whether the frames may come back in a later call (a cache pays only then).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from .config import StageConfig
from .records import MergedFrames, PairRegistrations
from .watchdog import watched

__all__ = ["LocatorConfig", "Locator", "LocatorContext", "named_frames"]


class LocatorConfig(StageConfig):
    """Config base of locators; ``build()`` returns a :class:`Locator`.

    A field whose name ends in ``_px`` is a length in sensor pixels, whatever resolution
    the merged frames are registered at: the framework builds the locator from a copy
    in merged-frame pixels (:func:`photonpano.budget.grid.in_merged_pixels`).
    """

    stage: ClassVar[str] = "locator"
    template_defaults: ClassVar[dict[str, Any]] = {}
    """Settings suggested for registering against a low-noise panorama (the ``mosaic``
    scheme's locator starts from them; fields the spec gives win)."""

    def converging(self) -> LocatorConfig:
        """This config with any stopping rule tuned for speed set to run each registration to convergence.

        The ``mosaic`` scheme builds the locator of its held-out chains from it
        (:mod:`photonpano.long_pairs`): a few dozen pairs of frames that overlap by only
        about 70 %, whose registrations measure a slow shape error of a few hundredths of
        a pixel per link, where a registration stopped early keeps part of the current
        estimate's error. The base returns the config itself (a locator without such a rule).
        """
        return self


@dataclass(frozen=True)
class LocatorContext:
    """How one locator call may run (passed by the framework; the default: serially, frames may return).

    Attributes:
        executor: an :class:`~photonpano.executor.Executor` on which independent
            per-frame or per-pair work may run, or None (run serially). A locator may
            ignore it.
        reuses_frames: False when each frame is used in this call only (the ``mosaic``
            scheme): a locator that caches per-frame data across calls may then skip
            its cache (and the cost of its keys).
    """

    executor: Any = None
    reuses_frames: bool = True


def _checked_initial(owner: str, initial: Any, count: int) -> NDArray[np.float64]:
    """``initial`` as (count, 3, 3) finite float64, or a one-line ValueError naming ``owner``."""
    initial = np.asarray(initial, np.float64)
    if initial.shape != (count, 3, 3):
        raise ValueError(f"{owner}: initial must be ({count}, 3, 3) for {count} pairs, got {initial.shape}")
    if not np.isfinite(initial).all():
        raise ValueError(f"{owner}: initial holds non-finite homographies")
    return initial


def named_frames(owner: str, merged: MergedFrames, pairs: Any) -> tuple[MergedFrames, NDArray[np.int64]]:
    """Resolve pairs that name frames by id into the frames they name and positions among these.

    Args:
        owner: who is calling, for the error message (e.g. ``"OpenCVSiftLocator.register_pairs"``).
        merged: the call's merged frames; frame i is named ``merged.frame_ids()[i]``
            (its id, or ``i`` when ``merged`` carries no ids).
        pairs: (P, 2) integer frame ids ``(a, b)``.

    Returns:
        ``(frames, positions)``: the frames the pairs name, each once and in ``merged``'s
        order (``merged`` itself when it names no other frame, or when P = 0; with their
        ids), and (P, 2) int64 positions of each pair's frames in ``frames``.

    Raises:
        TypeError: ``merged`` is not :class:`~photonpano.records.MergedFrames`.
        ValueError: ``pairs`` not (P, 2) integers, duplicate frame ids, or a pair naming
            a frame that is not in ``merged`` (one line naming ``owner``).
    """
    if not isinstance(merged, MergedFrames):
        raise TypeError(f"{owner}: merged must be MergedFrames, got {type(merged).__name__}")
    pairs = np.asarray(pairs)
    if pairs.dtype.kind not in "iu" or pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ValueError(f"{owner}: pairs must be (P, 2) integer frame ids, got {pairs.dtype} {pairs.shape}")
    if not len(pairs):
        return merged, np.zeros((0, 2), np.int64)
    ids = merged.frame_ids()
    order = np.argsort(ids, kind="stable")
    ordered = ids[order]
    if len(ids) > 1 and (ordered[1:] == ordered[:-1]).any():
        raise ValueError(f"{owner}: merged frames must carry distinct ids, frame id "
                         f"{int(ordered[1:][ordered[1:] == ordered[:-1]][0])} repeats")
    wanted = pairs.astype(np.int64, copy=False).ravel()
    at = np.minimum(np.searchsorted(ordered, wanted), max(len(ids) - 1, 0))
    missing = ~(ordered[at] == wanted) if len(ids) else np.ones(len(wanted), bool)
    if missing.any():
        p = int(np.flatnonzero(missing)[0]) // 2
        raise ValueError(f"{owner}: pair {p} {tuple(int(i) for i in pairs[p])} names a frame that is not among "
                         f"the {len(ids)} merged frames of this call (pairs name frames by merged.ids, or by "
                         "position without ids)")
    positions = order[at].reshape(-1, 2).astype(np.int64, copy=False)
    used = np.unique(positions)
    if len(used) == len(merged):
        return merged, positions
    return merged.take(used), np.searchsorted(used, positions).astype(np.int64, copy=False)


class Locator(abc.ABC):
    """Estimates homographies between merged frames (see the module).

    Subclasses implement :meth:`_register_pairs` (and may override
    :meth:`_register_to_template`); the framework calls the public methods, which
    validate their arguments and the result's length.
    """

    def register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                       context: LocatorContext | None = None) -> PairRegistrations:
        """Register each pair ``(a, b)`` of frames named by id: find H mapping frame b's pixels to frame a's.

        Pairs name frames, not positions in a buffer: ``a`` and ``b`` are frame ids,
        ``merged.ids`` (or positions ``0..G-1`` when ``merged`` carries no ids,
        :meth:`~photonpano.records.MergedFrames.frame_ids`). The framework's pairwise
        scheme gives every merged frame a new id and names each call's pairs by them,
        whatever it keeps in memory.

        Args:
            merged: (G) merged frames of this level with distinct ids (at pairwise levels the
                recent ones: the framework streams a level's frames in windows and calls
                once per window); frames no pair names are ignored.
            pairs: (P, 2) integer frame ids.
            initial: (P, 3, 3) float64 current estimate of each pair's homography (for
                direct methods or to guide matching; feature methods may ignore it).
            context: how the call may run (None: ``LocatorContext()``).

        Returns:
            One result per pair. A pair that cannot be registered is returned with
            ``ok=False``; raising is reserved for programming errors.

        Raises:
            TypeError, ValueError: bad arguments, e.g. a pair naming a frame not in
                ``merged`` (one line naming the locator), or a result of another length
                than ``pairs``.
        """
        owner = f"{type(self).__name__}.register_pairs"
        frames, positions = named_frames(owner, merged, pairs)
        initial = _checked_initial(owner, initial, len(positions))
        with watched("locator", self, "register_pairs"):  # a hung call ends the run (photonpano.watchdog)
            found = self._register_pairs(frames, positions, initial, context or LocatorContext())
        return self._result(owner, found, len(positions))

    def register_to_template(self, views: MergedFrames, frames: MergedFrames, initial: NDArray[np.float64],
                             context: LocatorContext | None = None) -> PairRegistrations:
        """Register each merged frame g against ``views[g]``: find H mapping frame g's pixels to view g's.

        Args:
            views: (G) the panorama rendered into each frame's grid (low noise, NaN and
                mask False where the panorama saw nothing).
            frames: (G) merged frames of the same shape.
            initial: (G, 3, 3) float64 current estimate of each registration.
            context: how the call may run (None: ``LocatorContext()``).

        Returns:
            G results (``ok=False`` where a frame could not be registered).

        Raises:
            TypeError, ValueError: bad arguments (one line naming the locator).
        """
        owner = f"{type(self).__name__}.register_to_template"
        if not isinstance(views, MergedFrames) or not isinstance(frames, MergedFrames):
            raise TypeError(f"{owner}: views and frames must be MergedFrames")
        if views.flux.shape != frames.flux.shape:
            raise ValueError(f"{owner}: views {views.flux.shape} and frames {frames.flux.shape} differ in shape")
        n = len(frames)
        initial = _checked_initial(owner, initial, n)
        with watched("locator", self, "register_to_template"):
            found = self._register_to_template(views, frames, initial, context or LocatorContext())
        return self._result(owner, found, n)

    @staticmethod
    def _result(owner: str, found: PairRegistrations, n: int) -> PairRegistrations:
        if not isinstance(found, PairRegistrations) or len(found.ok) != n:
            got = len(found.ok) if isinstance(found, PairRegistrations) else type(found).__name__
            raise ValueError(f"{owner}: expected PairRegistrations of {n} results, got {got}")
        return found

    @abc.abstractmethod
    def _register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                        context: LocatorContext) -> PairRegistrations:
        """Register validated pairs (see :meth:`register_pairs`).

        Args:
            merged: the frames the pairs name, each once (with the caller's ids, which
                :meth:`~photonpano.records.MergedFrames.content_key` uses).
            pairs: (P, 2) int64 positions of each pair's frames in ``merged``.
            initial: (P, 3, 3) float64 finite starts.
            context: how the call may run.

        Returns:
            (P) results; ``ok=False`` for a pair that cannot be registered.
        """

    def _register_to_template(self, views: MergedFrames, frames: MergedFrames, initial: NDArray[np.float64],
                              context: LocatorContext) -> PairRegistrations:
        """Register validated frames against their views (see :meth:`register_to_template`).

        The default registers the pairs (view g, frame g) of the two stacked by
        :meth:`_register_pairs`; a locator that prepares templates differently
        (e.g. no features on the low-noise view) overrides this.
        """
        n = len(frames)
        pairs = np.stack([np.arange(n), np.arange(n, 2 * n)], axis=1)
        return self._register_pairs(MergedFrames.concat(views, frames), pairs, initial, context)

    def cache_stats(self) -> dict[str, int]:
        """Return feature-cache counters (``{"hits", "misses", "entries", ...}``); {} if none is kept."""
        return {}

    def reset_cache_stats(self) -> None:
        """Zero the counters of :meth:`cache_stats` (a locator without a cache does nothing)."""

    def end_level(self) -> None:
        """Drop per-frame data kept across calls: the framework calls this when a level's registrations are done.

        The next level merges every frame anew, so nothing cached can be reused; the
        counters of :meth:`cache_stats` are kept. Default: nothing.
        """
