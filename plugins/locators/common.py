"""Shared machinery of the built-in locators: per-frame caches, feature pipelines, ECC polish.

Not a plugin (it registers nothing). Locators built on it:

- :class:`CachingLocator` keeps per-merged-frame data (features, prepared images) in a
  cache keyed by the *content* of the frame, so a frame registered by several calls of
  :meth:`~photonpano.stages.Locator.register_pairs` (the framework calls it once per
  window of groups, and a frame belongs to the pairs of a few consecutive calls) or a
  frame that did not change between levels is described once. :meth:`CachingLocator.cache_stats` reports
  hits and misses.
- :class:`DirectLocator` adds the direct recipe: prepare each frame once, register each pair
  from its initial estimate.
- :class:`FeatureLocator` adds the feature-based recipe: describe each frame once, match
  each pair, fit a robust motion model (:func:`robust_motion`), optionally polish it by ECC.

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

__all__ = ["Features", "PairResult", "FrameCache", "CachingLocator", "FeatureLocator", "PolishConfig",
           "frame_key", "to_registrations", "keypoint_mask", "ecc_image", "ecc_polish", "corner_change",
           "MotionModel", "MOTION_PARAMETERS", "robust_method", "robust_motion", "gric",
           "ratio_test_motion", "ratio_matches", "IntegralL2Matcher", "DirectLocator"]


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

        Each frame is described once per distinct content, whichever call needs it.
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
            return self.frame_data("ecc", i, lambda: ecc_image(merged.flux[i], merged.masks[i]), flux=True)

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
        """Register each pair starting from ``initial`` (see :meth:`Locator.register_pairs`)."""
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


def ecc_image(flux: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Return a merged flux image scaled to about [0, 1] (twice the mean trusted flux = 1) for ECC.

    Every observed pixel keeps its (possibly noisier) flux: zeroing the untrusted border
    would put false edges into the moving image and bias the alignment. Unobserved
    (NaN) pixels are 0.

    Args:
        flux: (H, W) float32 flux, NaN where unobserved.
        mask: (H, W) bool trusted pixels, used to pick the white level.

    Returns:
        (H, W) float32 image.

    Raises:
        ValueError: if ``flux`` and ``mask`` differ in shape.
    """
    from ._compiled import normalised_flux

    # ECC is invariant to gain and offset: the scale only keeps the numbers near 1. One
    # compiled pass (runs once per merged frame and panorama view, on the workers).
    flux, mask = np.ascontiguousarray(flux, np.float32), np.ascontiguousarray(mask, bool)
    if flux.shape != mask.shape:
        raise ValueError(f"ecc_image: flux {flux.shape} and mask {mask.shape} differ in shape")
    image = np.empty(flux.shape, np.float32)
    normalised_flux(flux.reshape(-1), mask.reshape(-1), image.reshape(-1))
    return image


def corner_change(h1: NDArray[np.float64], h2: NDArray[np.float64], width: int, height: int) -> float:
    """Return the largest distance (pixels) between the corners mapped by two homographies."""
    from photonpano import geometry

    moved = geometry.apply(np.stack([h1, h2]), geometry.corners(width, height))  # one call: each pair's ECC runs this
    change = np.abs(moved[0] - moved[1]).max()
    return float(change) if np.isfinite(change) else float("inf")


def ecc_polish(image_a: NDArray[np.float32], image_b: NDArray[np.float32], mask_a: NDArray[np.bool_],
               mask_b: NDArray[np.bool_], homography: NDArray[np.float64], *, iterations: int = 30, blur: int = 5,
               max_change_px: float = 2.0) -> NDArray[np.float64]:
    """Polish a homography (b to a) by ECC maximisation; return the input on failure.

    OpenCV's ``findTransformECCWithMask`` with frame b as the template: only pixels
    trusted in b whose warped position is trusted in a enter the correlation.

    Args:
        image_a: (H, W) float32 normalised flux of frame a (the moving image).
        image_b: (H, W) float32 normalised flux of frame b (the template).
        mask_a: (H, W) bool trusted pixels of frame a.
        mask_b: (H, W) bool trusted pixels of frame b.
        homography: (3, 3) float64 starting estimate mapping b's pixels to a's.
        iterations: maximum Gauss-Newton iterations.
        blur: Gaussian pre-filter size in pixels (made odd).
        max_change_px: a result moving a corner further than this from ``homography``
            (pixels) is discarded.

    Returns:
        (3, 3) float64 refined homography, or ``homography`` if ECC fails or moves a
        corner by more than ``max_change_px``.
    """
    import cv2

    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-5)
    try:
        _, warp = cv2.findTransformECCWithMask(image_b, image_a, mask_b.astype(np.uint8), mask_a.astype(np.uint8),
                                               homography.astype(np.float32), cv2.MOTION_HOMOGRAPHY, criteria,
                                               blur | 1)
    except cv2.error:  # did not converge
        return homography
    warp = warp.astype(np.float64) / warp[2, 2]
    h, w = image_b.shape
    return warp if corner_change(warp, homography, w, h) < max_change_px else homography


MotionModel = Literal["auto", "homography", "affine", "similarity"]
"""Motion models a feature locator can fit; ``auto`` picks one per pair by :func:`gric`."""

MOTION_PARAMETERS = {"homography": 8, "affine": 6, "similarity": 4}
"""Degrees of freedom of each motion model."""


def robust_method(name: str) -> int:
    """Return OpenCV's flag for a robust estimator name (``ransac``, ``usac-magsac``, ``usac-accurate``, ``lmeds``)."""
    import cv2

    return {"ransac": cv2.RANSAC, "usac-magsac": cv2.USAC_MAGSAC, "usac-accurate": cv2.USAC_ACCURATE,
            "lmeds": cv2.LMEDS}[name]


def gric(model: NDArray[np.float64], src: NDArray[np.float32], dst: NDArray[np.float32], sigma_px: float,
         parameters: int) -> float:
    """Torr's Geometric Robust Information Criterion of a 2D motion model (lower is better).

    ``GRIC = sum_i min(e_i^2 / sigma^2, 2 (r - d)) + lambda1 d n + lambda2 k`` with data
    dimension r = 4 (two image points), model dimension d = 2 (every model here maps
    points to points), ``lambda1 = ln r``, ``lambda2 = ln(r n)`` and k the model's degrees
    of freedom (Torr, "Bayesian model estimation and selection for epipolar geometry and
    generic manifold fitting", IJCV 50(1), 2002, Eq. 22). The residual term caps outliers,
    the parameter term charges each degree of freedom: a homography wins only where its
    extra parameters explain the data beyond the noise.

    Args:
        model: (3, 3) float64 mapping ``src`` to ``dst``.
        src: (N, 2) float32 points of frame b, pixels.
        dst: (N, 2) float32 matching points of frame a, pixels.
        sigma_px: standard deviation of keypoint positions, pixels.
        parameters: degrees of freedom k of the model.

    Returns:
        The criterion (dimensionless).
    """
    from ._compiled import capped_transfer_error  # compiled: 3 per pair at level 1, on the workers

    n = len(src)
    residual = capped_transfer_error(np.asarray(model, np.float64), src, dst, float(sigma_px) ** 2, 4.0)
    return float(residual + 2 * np.log(4) * n + np.log(4 * n) * parameters)


def robust_motion(src: NDArray[np.float32], dst: NDArray[np.float32], *, motion: str = "homography",
                  method: str = "usac-magsac", threshold_px: float = 1.5, min_inliers: int = 12,
                  refine: bool = True) -> PairResult:
    """Fit a motion model to tentative correspondences with an OpenCV robust estimator.

    Homographies are fitted by ``cv2.findHomography`` (refit to all inliers by least
    squares with ``refine``), affine and similarity models by ``cv2.estimateAffine2D`` and
    ``cv2.estimateAffinePartial2D`` (Levenberg-Marquardt on the inliers with ``refine``).
    With ``motion="auto"`` all three are fitted and the one of lowest :func:`gric` (keypoint
    noise ``threshold_px / 2``) is returned. This guards against degenerate
    configurations: when the static scene's keypoints lie on a thin band (a floor, a
    horizon), a homography can fit them *and* a few keypoints of an independently moving
    object, a lower-order model fitted to the band alone scores better.

    Args:
        src: (N, 2) float32 points of frame b (pixels, photonpano's convention).
        dst: (N, 2) float32 matching points of frame a.
        motion: ``homography``, ``affine``, ``similarity`` or ``auto``.
        method: robust estimator, see :func:`robust_method` (affine and similarity
            models use RANSAC unless ``lmeds``).
        threshold_px: inlier threshold in pixels.
        min_inliers: fewer inliers than this flags the pair as failed.
        refine: refit each model to its inliers.

    Returns:
        The pair's result: (3, 3) float64 homography mapping ``src`` to ``dst`` (of the
        chosen model), the number of correspondences and of the model's inliers.
    """
    import cv2

    fits: dict[str, tuple[NDArray[np.float64], int]] = {}
    for name in (("homography", "affine", "similarity") if motion == "auto" else (motion,)):
        if name == "homography":
            model, mask = cv2.findHomography(src, dst, robust_method(method), threshold_px, maxIters=5000,
                                             confidence=0.999)
            if model is not None and mask is not None and refine and mask.sum() >= 8:
                refined, _ = cv2.findHomography(src[mask.ravel() > 0], dst[mask.ravel() > 0], 0)
                model = refined if refined is not None else model
        else:
            estimate = cv2.estimateAffine2D if name == "affine" else cv2.estimateAffinePartial2D
            affine, mask = estimate(src, dst, method=cv2.LMEDS if method == "lmeds" else cv2.RANSAC,
                                    ransacReprojThreshold=threshold_px, maxIters=5000, confidence=0.999,
                                    refineIters=10 if refine else 0)
            model = None if affine is None else np.vstack([affine, [0.0, 0.0, 1.0]])
        if model is not None and mask is not None and np.all(np.isfinite(model)) and abs(model[2, 2]) > 1e-12:
            fits[name] = (model.astype(np.float64) / model[2, 2], int(mask.sum()))
    if not fits:
        return PairResult(matches=len(src))
    chosen = min(fits, key=lambda name: gric(fits[name][0], src, dst, threshold_px / 2, MOTION_PARAMETERS[name]))
    h, n_in = fits[chosen]
    ok = n_in >= min_inliers and abs(np.linalg.det(h[:2, :2])) > 1e-3
    return PairResult(h, len(src), n_in, bool(ok))


def ratio_test_motion(matcher: Any, points_a: NDArray, descriptors_a: NDArray, points_b: NDArray,
                      descriptors_b: NDArray, config: Any) -> PairResult:
    """Match descriptors of frame b to frame a, keep Lowe's ratio-test survivors, fit :func:`robust_motion`.

    Args:
        matcher: an OpenCV ``DescriptorMatcher`` (e.g. ``cv2.BFMatcher``) for the
            descriptors, or an :class:`IntegralL2Matcher` (see :func:`ratio_matches`).
        points_a: (Ka, 2) keypoints of frame a, pixels (photonpano's convention).
        descriptors_a: (Ka, D) their descriptors.
        points_b: (Kb, 2) keypoints of frame b.
        descriptors_b: (Kb, D) their descriptors.
        config: the locator's config, with ``ratio``, ``min_inliers``, ``motion``,
            ``method``, ``reprojection_px`` and ``refine``.

    Returns:
        The pair's result (b to a); failed (``ok=False``) with fewer than four keypoints
        in a frame or fewer than ``max(4, min_inliers)`` ratio-test matches.
    """
    if len(points_a) < 4 or len(points_b) < 4:
        return PairResult()
    query, train = ratio_matches(matcher, descriptors_b, descriptors_a, config.ratio)
    if len(query) < max(4, config.min_inliers):
        return PairResult(matches=len(query))
    src = np.asarray(points_b, np.float32)[query]
    dst = np.asarray(points_a, np.float32)[train]
    return robust_motion(src, dst, motion=config.motion, method=config.method, threshold_px=config.reprojection_px,
                         min_inliers=config.min_inliers, refine=config.refine != "none")


def ratio_matches(matcher: Any, descriptors_query: NDArray, descriptors_train: NDArray,
                  ratio: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Lowe's ratio test: each query descriptor's nearest train descriptor, if clearly the nearest.

    Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004, Sec. 7.1:
    a match is kept when its distance is below ``ratio`` times the second-nearest's.

    Args:
        matcher: an OpenCV ``DescriptorMatcher`` (its ``knnMatch`` with k = 2), or an
            object with this function's signature as a ``ratio_matches`` method
            (:class:`IntegralL2Matcher`).
        descriptors_query: (Kq, D) descriptors of the query frame (frame b of a pair).
        descriptors_train: (Kt, D) descriptors of the train frame (frame a).
        ratio: the threshold, in (0, 1).

    Returns:
        ``(query, train)``: (M,) int64 indices of the kept matches, in query order.
    """
    if hasattr(matcher, "ratio_matches"):
        return matcher.ratio_matches(descriptors_query, descriptors_train, ratio)
    knn = matcher.knnMatch(descriptors_query, descriptors_train, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    return (np.array([m.queryIdx for m in good], np.int64).reshape(-1),
            np.array([m.trainIdx for m in good], np.int64).reshape(-1))


class IntegralL2Matcher:
    """Brute-force L2 matching of integer-valued descriptors (OpenCV SIFT's) as one BLAS product.

    OpenCV's SIFT descriptors are 128 integers in 0..255 stored as float32, so every
    squared distance ``|q|^2 - 2 q.t + |t|^2`` and every partial sum of it is an integer
    below 2**24, exact in float32 whatever order the matrix product sums in: the
    distances, hence the ratio test's decisions, are those of
    ``cv2.BFMatcher(cv2.NORM_L2)`` (a tie for the nearest fails the test either way), at
    about a fifth of its time (300 x 300 SIFT descriptors: 0.32 against 1.7 ms on one
    core). It assumes what :meth:`exact` checks (the caller checks each frame's
    descriptors once, e.g. when describing it): other float32 descriptors would be
    matched with rounded distances.

    Run it with the BLAS limited to one thread inside a thread pool (the
    :class:`~photonpano.executor.ThreadExecutor` does): OpenBLAS's own threads,
    called from two threads at once, ran it 2.4x slower.
    """

    @staticmethod
    def exact(descriptors: NDArray) -> bool:
        """Whether the (K, D) float32 descriptors are integers whose squared distances are exact in float32."""
        d = np.asarray(descriptors)
        if d.ndim != 2 or d.dtype != np.float32 or not d.size:
            return False
        low, high = float(d.min()), float(d.max())
        return low >= 0 and 2 * d.shape[1] * high * high < 2 ** 24 and bool(np.array_equal(d, np.rint(d)))

    def ratio_matches(self, descriptors_query: NDArray, descriptors_train: NDArray,
                      ratio: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """:func:`ratio_matches` for (Kq, D) and (Kt, D) float32 descriptors that are :meth:`exact`."""
        q, t = np.asarray(descriptors_query, np.float32), np.asarray(descriptors_train, np.float32)
        if len(t) < 2:  # knnMatch's rule: no second neighbour, no match
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        squared = q @ t.T
        squared *= -2
        squared += np.einsum("ij,ij->i", t, t)[None]
        squared += np.einsum("ij,ij->i", q, q)[:, None]
        rows = np.arange(len(q))
        nearest = squared.argmin(axis=1)
        first = squared[rows, nearest]
        squared[rows, nearest] = np.inf
        second = squared.min(axis=1)
        # distances as OpenCV's (float32 square roots), compared in double as the knnMatch path is
        keep = np.sqrt(first).astype(np.float64) < ratio * np.sqrt(second).astype(np.float64)
        query = np.flatnonzero(keep)
        return query, nearest[query].astype(np.int64)
