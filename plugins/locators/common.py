"""Shared machinery of the built-in locators: per-frame caches, feature pipelines, ECC polish.

Not a plugin (it registers nothing). Locators built on it:

- :class:`CachingLocator` keeps per-merged-frame data (features, prepared images) in a
  cache keyed by the *content* of the frame, so a frame registered by several calls of
  :meth:`~photonpano.stages.Locator.register_pairs` (the framework calls it once per
  window of groups, and a frame belongs to the pairs of a few consecutive calls; its
  pairs name frames by id and the locator gets the named frames, so a frame's position
  differs from call to call and the key is its content id, ``merged.ids``) or a
  frame that did not change between levels is described once. :meth:`CachingLocator.cache_stats` reports
  hits and misses.
- :class:`DirectLocator` adds the direct recipe: prepare each frame once, register each pair
  from its initial estimate.
- :class:`FeatureLocator` adds the feature-based recipe: describe each frame once, match
  each pair, fit a robust motion model (:mod:`~photonpano.plugins.locators.matching`),
  optionally polish it by ECC (:mod:`~photonpano.plugins.locators.polish`).

Only numpy at module level; OpenCV is imported inside functions.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano.stages import Locator, LocatorConfig, LocatorContext, MergedFrames, PairRegistrations
from pydantic import Field

from .polish import ecc_image, ecc_polish

__all__ = ["Features", "PairResult", "FrameCache", "CachingLocator", "FeatureLocator", "PolishConfig",
           "frame_key", "to_registrations", "keypoint_mask", "DirectLocator"]


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one merged frame.

    Attributes:
        points: (K, 2) float64 ``(x, y)`` keypoint positions in pixels, photonpano's
            convention (x right, y down, pixel centres at integers); K may be 0.
        descriptors: (K, D) descriptors in the backend's own type (numpy array, torch
            tensor, ...), row k describing ``points[k]``.
        native: anything else the backend needs to match (e.g. its own keypoint objects).
    """

    points: NDArray[np.float64]
    descriptors: Any
    native: Any = None

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class PairResult:
    """The registration of one pair ``(a, b)``.

    Attributes:
        homography: (3, 3) float64 mapping frame b's pixels to frame a's, ``H[2, 2] == 1``
            (the identity when failed).
        matches: tentative correspondences (0 for direct methods).
        inliers: correspondences consistent with the homography (for direct methods: the
            number of trusted pixels of b that land inside a, a weight for the pose graph).
        ok: False if the pair failed to register.
    """

    homography: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    matches: int = 0
    inliers: int = 0
    ok: bool = False


def frame_key(merged: MergedFrames, index: int, *, flux: bool = False) -> bytes:
    """Return a cache key of merged frame ``index``'s content (:meth:`MergedFrames.content_key`).

    Args:
        merged: the merged frames.
        index: frame index into ``merged``.
        flux: key data derived from the float32 flux (instead of the uint8 image and
            the mask).

    Returns:
        The frame's id (``merged.ids``) or a 16-byte digest; equal keys mean identical frames.
    """
    return merged.content_key(index, flux=flux)


class FrameCache:
    """Content-keyed cache of per-frame data with hit and miss counters.

    Entries live until :meth:`retain` drops those whose frames are no longer current, so
    the cache holds at most the frames of one call.
    """

    def __init__(self) -> None:
        self._data: dict[tuple[bytes, ...], Any] = {}
        self.hits = 0
        self.misses = 0

    def get(self, key: tuple[bytes, ...], compute: Any) -> Any:
        """Return the entry of ``key``, computing it with ``compute()`` on a miss.

        Args:
            key: ``(frame_key, ...)``: the frame's :func:`frame_key` first, then anything
                else the data depends on.
            compute: zero-argument callable.
        """
        if key in self._data:
            self.hits += 1
            return self._data[key]
        self.misses += 1
        value = self._data[key] = compute()
        return value

    def retain(self, frames: set[bytes]) -> None:
        """Drop every entry whose frame key (first element) is not in ``frames``."""
        for key in [k for k in self._data if k[0] not in frames]:
            del self._data[key]

    def __len__(self) -> int:
        return len(self._data)


class CachingLocator(Locator):
    """A locator with a content-keyed per-frame cache and its statistics.

    At the start of each call a subclass calls :meth:`begin` with the frames it will use
    and the call's :class:`~photonpano.locator.LocatorContext` (this evicts data of frames
    that are gone), then :meth:`frame_data` to get per-frame data, computed once per
    distinct frame content (or every time, when the context says no frame comes back).
    :meth:`cache_stats` is what the pipeline reports per level.
    """

    def __init__(self) -> None:
        self._caches: dict[str, FrameCache] = {}
        self._merged: MergedFrames | None = None
        self._keys: dict[tuple[int, bool], tuple[bytes, ...]] = {}
        self._reuse = True

    def begin(self, merged: MergedFrames, indices: NDArray[np.int64], context: LocatorContext) -> None:
        """Start a batch on ``merged``: key its frames ``indices`` and evict other frames' data."""
        self._merged = merged
        self._keys = {}
        self._reuse = context.reuses_frames
        if not self._reuse:  # every frame is used in this call only: no cache, no keys
            return
        keys = set()
        for i in np.unique(np.asarray(indices, dtype=np.int64)):
            keys.add(self._key(int(i), False)[0])
        for cache in self._caches.values():
            cache.retain(keys)

    def _key(self, index: int, flux: bool) -> tuple[bytes, ...]:
        if (index, flux) not in self._keys:
            base = self._key(index, False)[0] if flux else frame_key(self._merged, index)
            self._keys[(index, flux)] = (base, frame_key(self._merged, index, flux=True)) if flux else (base,)
        return self._keys[(index, flux)]

    def frame_data(self, kind: str, index: int, compute: Any, *, flux: bool = False) -> Any:
        """Return ``compute()`` for frame ``index`` of the current batch, cached by content.

        Args:
            kind: cache name (``"features"``, ``"ecc"``, ...); each kind has its own cache.
            index: frame index into the ``merged`` given to :meth:`begin`.
            compute: zero-argument callable computing the data on a miss.
            flux: whether the data depends on the flux (then the flux is part of the key).
        """
        if self._merged is None:
            raise RuntimeError("CachingLocator.frame_data called before begin()")
        cache = self._caches.setdefault(kind, FrameCache())
        if not self._reuse:
            cache.misses += 1
            return compute()
        return cache.get(self._key(index, flux), compute)

    @property
    def exposure_s(self) -> float | None:
        """The current batch's binary frame exposure in seconds (:class:`MergedFrames` ``exposure_s``), or None.

        None outside a batch and for intensity frames; a locator's per-frame preparation
        (:meth:`frame_data`'s ``compute``) may use it to weigh pixels by their binomial noise.
        """
        return None if self._merged is None else self._merged.exposure_s

    def finish(self) -> None:
        """End the batch started by :meth:`begin` (drops the reference to the merged frames)."""
        self._merged = None
        self._keys = {}

    def cache_stats(self) -> dict[str, int]:
        """Return cache counters since the locator was built (or last reset).

        Returns:
            ``{"hits": n, "misses": n, "entries": n}`` summed over the cache kinds: a miss
            is one frame described (or prepared), a hit one description reused; entries
            are held now. Per-kind counters are added as ``"<kind>_hits"`` and
            ``"<kind>_misses"``.
        """
        stats = {"hits": 0, "misses": 0, "entries": 0}
        for kind, cache in sorted(self._caches.items()):
            stats["hits"] += cache.hits
            stats["misses"] += cache.misses
            stats["entries"] += len(cache)
            stats[f"{kind}_hits"], stats[f"{kind}_misses"] = cache.hits, cache.misses
        return stats

    def reset_cache_stats(self) -> None:
        """Zero the counters of :meth:`cache_stats` (the cached data is kept)."""
        for cache in self._caches.values():
            cache.hits = cache.misses = 0

    def end_level(self) -> None:
        """Drop the cached data (the counters are kept; see :meth:`Locator.end_level`)."""
        for cache in self._caches.values():
            cache.retain(set())


class PolishConfig(LocatorConfig):
    """Config base of feature locators with the optional least-squares or ECC polish."""

    refine: Literal["none", "lm", "ecc"] = "ecc"
    """Polish of the robust estimate: ``lm`` refits it to all inliers by least squares;
    ``ecc`` then maximises the enhanced correlation coefficient between the two merged flux
    images (a dense sub-pixel refinement that keeps the feature result if it fails)."""
    ecc_iterations: Annotated[int, Field(gt=0)] = 30
    """ecc: maximum Gauss-Newton iterations per pair."""
    ecc_blur: Annotated[int, Field(ge=1, le=15)] = 5
    """ecc: size of the Gaussian pre-filter in pixels (odd, 1 = none); merged frames are noisy."""
    ecc_max_change_px: Annotated[float, Field(gt=0)] = 2.0
    """ecc: a refinement that moves a frame corner further than this (pixels) from the
    feature estimate is discarded as a divergence."""


class FeatureLocator(CachingLocator):
    """Feature-based locator: per-frame features (cached), per-pair match and estimate.

    Subclasses implement :meth:`describe` and :meth:`match`; frames are described and
    pairs matched on the call's executor (:class:`~photonpano.locator.LocatorContext`) unless the
    subclass sets ``thread_safe = False``. If the config has a ``refine``
    field equal to ``"ecc"``, successful pairs are polished by :func:`ecc_polish` with the
    config's ``ecc_iterations``, ``ecc_blur`` and ``ecc_max_change_px``.

    Args:
        config: the plugin's config.
    """

    thread_safe: bool = True
    """Whether :meth:`describe` and :meth:`match` may run concurrently on one instance."""

    def __init__(self, config: LocatorConfig) -> None:
        super().__init__()
        self.config = config

    @abc.abstractmethod
    def describe(self, image: NDArray[np.uint8], mask: NDArray[np.bool_],
                 flux: NDArray[np.float32]) -> Features:
        """Detect and describe keypoints of one merged frame.

        Args:
            image: (H, W) uint8 tone-mapped merged frame.
            mask: (H, W) bool trusted pixels; keypoints must lie inside.
            flux: (H, W) float32 linear flux, NaN where unobserved (most backends use
                ``image`` only).

        Returns:
            The frame's features, points in photonpano's pixel convention.
        """

    @abc.abstractmethod
    def match(self, feat_a: Features, feat_b: Features) -> PairResult:
        """Estimate the homography mapping frame b's pixels to frame a's from features.

        Failures are returned as ``PairResult(ok=False)``, never raised.
        """

    def _register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                        context: LocatorContext) -> PairRegistrations:
        """Register each pair (see :meth:`Locator.register_pairs`); ``initial`` is unused.

        ``pairs`` are positions in ``merged``, the frames the call's ids named
        (:meth:`Locator._register_pairs`). Each frame is described once per distinct
        content, whichever call needs it and wherever it sits in that call's ``merged``.
        """
        self.begin(merged, pairs, context)
        try:
            return self._matched(merged, pairs, context)
        finally:
            self.finish()

    def _matched(self, merged: MergedFrames, pairs: NDArray[np.int64], context: LocatorContext
                 ) -> PairRegistrations:
        from photonpano.executor import SerialExecutor

        executor = (context.executor if self.thread_safe else None) or SerialExecutor()
        frames = [int(i) for i in np.unique(pairs)]

        def describe(i: int) -> Features:
            return self.frame_data("features", i,
                                   lambda: self.describe(merged.images[i], merged.masks[i], merged.flux[i]))

        # each distinct frame once, then the pairs, both on the executor
        feats = dict(zip(frames, executor.map(describe, frames)))
        results = executor.map(lambda ab: self.match(feats[int(ab[0])], feats[int(ab[1])]), pairs)
        if getattr(self.config, "refine", "none") != "ecc":
            return to_registrations(results)

        def ecc(i: int) -> NDArray[np.float32]:
            return self.frame_data("ecc", i, lambda: ecc_image(merged.flux[i], merged.masks[i], merged.exposure_s),
                                   flux=True)

        def polish(result: PairResult, a: int, b: int) -> PairResult:
            if not result.ok:
                return result
            polished = ecc_polish(ecc(int(a)), ecc(int(b)), merged.masks[a], merged.masks[b], result.homography,
                                  iterations=self.config.ecc_iterations, blur=self.config.ecc_blur,
                                  max_change_px=self.config.ecc_max_change_px)
            return PairResult(polished, result.matches, result.inliers, True)

        return to_registrations(executor.map(polish, results, pairs[:, 0], pairs[:, 1]))


class DirectLocator(CachingLocator):
    """A direct (intensity-based) locator: per-frame prepared data, each pair from its start.

    Each distinct frame is prepared once (:meth:`prepare`, cached under
    :attr:`prepared_kind`), then every pair is registered by :meth:`register` starting
    from the framework's ``initial`` estimate.
    """

    prepared_kind: str = "prepared"
    """Cache name of the prepared frames (``<kind>_hits`` / ``<kind>_misses`` in :meth:`cache_stats`)."""

    @abc.abstractmethod
    def prepare(self, flux: NDArray[np.float32], mask: NDArray[np.bool_]) -> Any:
        """Prepare one merged frame ((H, W) float32 flux, NaN where unobserved; (H, W) bool trusted)."""

    @abc.abstractmethod
    def register(self, prepared_a: Any, prepared_b: Any, initial: NDArray[np.float64]) -> PairResult:
        """Register one pair: frame a (moving) and b (template) as prepared, (3, 3) float64 start b to a."""

    def _register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                        context: LocatorContext) -> PairRegistrations:
        """Register each pair starting from ``initial`` (see :meth:`Locator.register_pairs`).

        ``pairs`` are positions in ``merged``, the frames the call's ids named
        (:meth:`Locator._register_pairs`); each frame is prepared once per distinct content.
        """
        self.begin(merged, pairs, context)
        try:
            def frame(i: int) -> Any:
                return self.frame_data(self.prepared_kind, i, lambda: self.prepare(merged.flux[i], merged.masks[i]),
                                       flux=True)

            return to_registrations([self.register(frame(int(a)), frame(int(b)), np.asarray(h, np.float64))
                                     for (a, b), h in zip(pairs, initial)])
        finally:
            self.finish()


def to_registrations(results: list[PairResult]) -> PairRegistrations:
    """Stack per-pair results into a :class:`~photonpano.stages.PairRegistrations`."""
    return PairRegistrations(
        homographies=np.array([r.homography for r in results], dtype=np.float64).reshape(-1, 3, 3),
        matches=np.array([r.matches for r in results], dtype=np.int64),
        inliers=np.array([r.inliers for r in results], dtype=np.int64),
        ok=np.array([r.ok for r in results], dtype=bool),
    )


def keypoint_mask(mask: NDArray[np.bool_], margin_px: int = 4) -> NDArray[np.uint8]:
    """Return the trusted mask eroded by ``margin_px`` pixels, as OpenCV's uint8 mask.

    Keypoints near the edge of the trusted region describe patches that reach into
    unobserved pixels; the erosion keeps them out.

    Args:
        mask: (H, W) bool trusted pixels.
        margin_px: erosion radius in pixels (a (2r+1) square).

    Returns:
        (H, W) uint8, 1 where keypoints may lie.
    """
    import cv2

    size = 2 * margin_px + 1
    return cv2.erode(mask.astype(np.uint8), np.ones((size, size), np.uint8))
