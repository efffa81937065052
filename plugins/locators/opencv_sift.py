"""Locator ``opencv-sift``: SIFT features, Lowe's ratio test and a robust homography.

This is the paper's locator (Sec. 5, "Implementation Details": OpenCV SIFT and RANSAC
homography fitting between merged frames). Features are computed once per merged frame
(cached by content across calls, see ``common.CachingLocator``) and reused by every pair
the frame belongs to.
"""

from __future__ import annotations

import threading
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.stages import LocatorConfig
from pydantic import Field

from .common import FeatureLocator, Features, PairResult, keypoint_mask
from .matching import IntegralL2Matcher, MotionModel, ratio_test_motion

__all__ = ["OpenCVSiftConfig", "OpenCVSiftLocator", "feature_budget", "PIXELS_PER_FEATURE", "MIN_FEATURES"]

PIXELS_PER_FEATURE = 64
"""``max_features: auto`` keeps one keypoint per this many pixels of the detection image."""
MIN_FEATURES = 200
"""``max_features: auto`` keeps at least this many keypoints (small frames)."""


def feature_budget(max_features: int | str, shape: tuple[int, ...]) -> int:
    """Keypoints to keep in an image of ``shape`` (rows, columns) pixels.

    Args:
        max_features: the config's value: a count (0 = all) or ``"auto"``.
        shape: the detection image's (H, W) in pixels.

    Returns:
        ``max_features`` itself, or for ``"auto"`` ceil(H W / :data:`PIXELS_PER_FEATURE`),
        at least :data:`MIN_FEATURES`.
    """
    if max_features != "auto":
        return int(max_features)
    return max(MIN_FEATURES, -(-shape[0] * shape[1] // PIXELS_PER_FEATURE))


class OpenCVSiftConfig(LocatorConfig):
    """OpenCV SIFT + ratio test + RANSAC/USAC homography between merged frames."""

    plugin: Literal["opencv-sift"] = "opencv-sift"
    max_features: Annotated[int, Field(ge=0)] | Literal["auto"] = "auto"
    """Keypoints kept per merged frame, strongest first (0 = all). ``auto``: one per
    :data:`PIXELS_PER_FEATURE` pixels of the image SIFT detects in (after
    ``image_scale``), at least :data:`MIN_FEATURES`: 493 for a merged frame of 127 x 248
    (a 254 x 496 sensor registered at the default binning 2), so that the cost of a level
    depends on the frames' size, not on the scene's texture. Describing and matching
    dominate level 1 and grow with the keypoints (a texture-rich city: 735 per merged
    frame; the bundled office: 256); on 24 captures of the evaluation suite (2026-11-25)
    the cap changed only the texture-rich ones, by -0.004 to +0.012 px (city, gravel,
    grass, mountains), and 100 000 frames of the city's zigzag took 12.7 s instead of
    14.2 (2000, the former default; median of four paired runs)."""
    image_scale: Annotated[float, Field(gt=0, le=1)] = 1.0
    """Merged frames are resized by this factor (area averaging) before detection, and
    keypoints mapped back to the merged frame's pixels. OpenCV's SIFT upsamples its
    input 2x, so at half the sensor resolution (the default ``registration_binning: 2``,
    or 0.5 here with ``registration_binning: 1``) it detects at the sensor's own
    resolution, about 4x faster than full resolution; the first level only initialises
    the later levels' refinement against the panorama. For the finest keypoints (e.g.
    with ``level_schemes: [pairwise]``) use ``registration_binning: 1`` and keep 1.0 here."""
    contrast_threshold: Annotated[float, Field(gt=0)] = 0.02
    """SIFT contrast threshold (OpenCV's default is 0.04; merged frames are low-contrast)."""
    ratio: Annotated[float, Field(gt=0, lt=1)] = 0.75
    """Lowe ratio-test threshold (dimensionless)."""
    method: Literal["ransac", "usac-magsac", "usac-accurate", "lmeds"] = "usac-magsac"
    """Robust estimator of the homography."""
    reprojection_px: Annotated[float, Field(gt=0)] = 1.5
    """Inlier threshold of the robust estimator, in pixels."""
    motion: MotionModel = "auto"
    """Motion model between merged frames: ``homography`` (the paper's), ``affine``,
    ``similarity``, or ``auto``: all three, the one of lowest GRIC per pair (Torr 2002)
    among those with at least 3 inliers per degree of freedom (the similarity always;
    ``matching.INLIERS_PER_PARAMETER``), which rejects homographies that bend to fit a few
    keypoints of a moving object when the static scene's keypoints lie on a thin band, and
    those that gather a few chance inliers among mostly wrong matches in the dark (the
    evaluation suite's captures at flux 0.05: RMSE geometric mean -13 %, a room 0.423 ->
    0.064 px)."""
    min_inliers: Annotated[int, Field(ge=4)] = 12
    """A pair with fewer inliers is flagged as failed (and bridged)."""
    refine: Literal["none", "lm", "ecc"] = "lm"
    """Polish of the robust estimate: ``lm`` refits it to all inliers by least squares
    (Levenberg-Marquardt, the paper's setting); ``ecc`` then maximises the enhanced
    correlation coefficient between the two merged flux images (Evangelidis and Psarakis,
    2008), a dense sub-pixel refinement that keeps the feature result if it fails. With
    the default ``level_schemes`` the later levels refine against the panorama anyway;
    ``ecc`` pays off when every level registers pairs (``level_schemes: [pairwise]``)."""
    ecc_iterations: Annotated[int, Field(gt=0)] = 30
    """ecc: maximum Gauss-Newton iterations per pair."""
    ecc_blur: Annotated[int, Field(ge=1, le=15)] = 9
    """ecc: size of the Gaussian pre-filter in pixels (odd, 1 = none). Merged frames are
    noisy: 9 keeps the panorama within 1 dB of the true-homography one down to 0.05
    photons/pixel/frame at m = 500 (5 is slightly sharper at high light, see docs/accuracy.md)."""
    ecc_max_change_px: Annotated[float, Field(gt=0)] = 2.0
    """ecc: a refinement that moves a frame corner further than this (pixels) from the
    feature estimate is discarded as a divergence."""

    def build(self) -> OpenCVSiftLocator:
        """Return the locator."""
        return OpenCVSiftLocator(self)


class OpenCVSiftLocator(FeatureLocator):
    """Registers pairs of merged frames with SIFT (see :class:`OpenCVSiftConfig`).

    Features are cached by frame content (see ``common.CachingLocator``): a frame used by
    consecutive calls of a level is described once;
    :meth:`cache_stats` counts hits and misses.
    """

    config: OpenCVSiftConfig

    def __init__(self, config: OpenCVSiftConfig) -> None:
        import cv2

        super().__init__(config)
        self._sift_by_budget: dict[int, Any] = {}  # keypoint budget -> cv2.SIFT (one per frame size in practice)
        self._sift_lock = threading.Lock()
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)
        self._exact_matcher = IntegralL2Matcher()

    def features(self, image: NDArray[np.uint8], mask: NDArray[np.bool_]):
        """Detect and describe SIFT keypoints of one merged frame.

        Args:
            image: (H, W) uint8 tone-mapped merged frame.
            mask: (H, W) bool pixels where keypoints may lie.

        Returns:
            ``(points, descriptors)``: (K, 2) float32 ``(x, y)`` pixel coordinates and
            (K, 128) float32 descriptors (K may be 0).
        """
        import cv2

        allowed = keypoint_mask(mask, 4)
        scale = self.config.image_scale
        if scale != 1.0:
            size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            allowed = cv2.resize(allowed, size, interpolation=cv2.INTER_NEAREST)
        keypoints, descriptors = self._detector(image.shape).detectAndCompute(image, allowed)
        if descriptors is None or not keypoints:
            return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
        points = cv2.KeyPoint_convert(keypoints)  # (K, 2) float32, in C++ (a list of k.pt held the GIL 0.1 ms)
        # OpenCV's SIFT first doubles the image (pixel x -> 2 x + 0.5) but halves keypoints back
        # as x / 2: they sit 0.25 px right of and below their features (measured: 0.77 px corner
        # error on a half turn, photonpano.testing.LocatorContract.test_pixel_centres_at_integers)
        points -= np.float32(0.25)
        # pixel centres at integers: resized pixel x_s covers full-resolution (x_s + 0.5) / s - 0.5
        return (points + 0.5) / np.float32(scale) - 0.5 if scale != 1.0 else points, descriptors

    def _detector(self, shape: tuple[int, ...]):
        """The ``cv2.SIFT`` keeping :func:`feature_budget` keypoints in an image of ``shape``."""
        import cv2

        budget = feature_budget(self.config.max_features, shape)
        with self._sift_lock:
            if budget not in self._sift_by_budget:
                self._sift_by_budget[budget] = cv2.SIFT_create(nfeatures=budget,
                                                               contrastThreshold=self.config.contrast_threshold)
            return self._sift_by_budget[budget]

    def describe(self, image: NDArray[np.uint8], mask: NDArray[np.bool_],
                 flux: NDArray[np.float32]) -> Features:
        """Return :meth:`features` as :class:`Features` (``flux`` is unused).

        Whether the descriptors are integers that :class:`IntegralL2Matcher` matches
        exactly (OpenCV's are) is checked here, once per frame.
        """
        points, descriptors = self.features(image, mask)
        return Features(points.astype(np.float64), descriptors,
                        native=(points, descriptors, IntegralL2Matcher.exact(descriptors)))

    def match(self, feat_a, feat_b) -> PairResult:
        """Estimate the homography mapping frame b's pixels to frame a's.

        Args:
            feat_a: frame a's :class:`Features` (or the ``(points, descriptors)`` tuple of
                :meth:`features`).
            feat_b: frame b's.

        Returns:
            The pair's result; ``homography`` is (3, 3) float64.
        """
        (pts_a, desc_a, exact_a), (pts_b, desc_b, exact_b) = _native(feat_a), _native(feat_b)
        # both frames' descriptors exact integers (checked by describe): the same matches, faster
        matcher = self._exact_matcher if exact_a and exact_b else self._matcher
        return ratio_test_motion(matcher, pts_a, desc_a, pts_b, desc_b, self.config)


def _native(features):
    """``(points, descriptors, exact)`` of :class:`Features` or of a :meth:`~OpenCVSiftLocator.features` tuple."""
    if isinstance(features, Features):
        return features.native
    points, descriptors = features
    return points, descriptors, False


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``opencv-sift``."""
    return [OpenCVSiftConfig]
