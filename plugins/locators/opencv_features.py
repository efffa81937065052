"""Locator ``opencv-orb``: binary features, faster than SIFT.

Same recipe as ``opencv-sift`` (describe each merged frame once, ratio-test matching,
a robust homography, optional least-squares and ECC polish), with ORB (Rublee et al.,
2011: oriented FAST corners and rotated BRIEF descriptors) matched by Hamming distance.
:class:`OpenCVBinaryLocator` takes any OpenCV binary ``Feature2D``; AKAZE is not offered
because OpenCV 5 moved it out of the main package (``opencv-contrib-python``).

OpenCV is imported when the locator is built, not when the plugin is registered.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.stages import LocatorConfig
from pydantic import Field

from .common import FeatureLocator, Features, PairResult, PolishConfig, keypoint_mask
from .matching import MotionModel, ratio_test_motion

__all__ = ["OpenCVOrbConfig", "OpenCVBinaryLocator"]


class _BinaryFeatureConfig(PolishConfig):
    """Fields shared by the binary-feature locators."""

    ratio: Annotated[float, Field(gt=0, lt=1)] = 0.8
    """Lowe ratio-test threshold on Hamming distances (dimensionless)."""
    method: Literal["ransac", "usac-magsac", "usac-accurate", "lmeds"] = "usac-magsac"
    """Robust estimator of the homography."""
    reprojection_px: Annotated[float, Field(gt=0)] = 1.5
    """Inlier threshold of the robust estimator, in pixels."""
    motion: MotionModel = "auto"
    """Motion model between merged frames: ``homography``, ``affine``, ``similarity``, or
    ``auto`` (the one of lowest GRIC per pair; see ``opencv-sift``)."""
    min_inliers: Annotated[int, Field(ge=4)] = 12
    """A pair with fewer inliers is flagged as failed (and bridged)."""
    border_px: Annotated[int, Field(ge=0)] = 8
    """Keypoints closer than this (pixels) to untrusted pixels are dropped."""


class OpenCVOrbConfig(_BinaryFeatureConfig):
    """OpenCV ORB (oriented FAST + rotated BRIEF) + ratio test + robust homography."""

    plugin: Literal["opencv-orb"] = "opencv-orb"
    max_features: Annotated[int, Field(gt=0)] = 2000
    """Keypoints kept per merged frame, strongest first. Brute-force Hamming matching
    costs grow with its square (5000 keypoints match ~6x slower than 2000); with 1000,
    low-light merged frames (flux 0.05) give wrong matches that pass RANSAC."""
    fast_threshold: Annotated[int, Field(ge=1, le=255)] = 5
    """FAST corner threshold in grey levels (OpenCV's default is 20; merged frames are
    low-contrast)."""
    levels: Annotated[int, Field(ge=1, le=16)] = 4
    """Pyramid levels of the detector (the motion between merged frames is nearly
    scale-free, so few are needed)."""
    scale_factor: Annotated[float, Field(gt=1, le=2)] = 1.2
    """Scale ratio between pyramid levels."""

    def build(self) -> OpenCVBinaryLocator:
        """Return the locator."""
        import cv2

        # edgeThreshold = patchSize = 31 (OpenCV's defaults): the descriptor patch
        return OpenCVBinaryLocator(self, cv2.ORB_create(
            nfeatures=self.max_features, scaleFactor=self.scale_factor, nlevels=self.levels,
            fastThreshold=self.fast_threshold))



class OpenCVBinaryLocator(FeatureLocator):
    """Registers pairs with an OpenCV binary detector-descriptor (ORB).

    Args:
        config: the plugin's config (an :class:`OpenCVOrbConfig`).
        detector: the OpenCV ``Feature2D`` object.
        max_features: keep the strongest keypoints only (0 = all).
    """

    def __init__(self, config: _BinaryFeatureConfig, detector, max_features: int = 0) -> None:
        import cv2

        super().__init__(config)
        self._detector = detector
        self._max_features = max_features
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def describe(self, image: NDArray[np.uint8], mask: NDArray[np.bool_],
                 flux: NDArray[np.float32]) -> Features:
        """Detect and describe keypoints (see :meth:`FeatureLocator.describe`).

        Returns:
            Features with (K, 2) float64 points and (K, 32) uint8 descriptors.
        """
        import cv2

        allowed = keypoint_mask(mask, self.config.border_px)
        keypoints, descriptors = self._detector.detectAndCompute(image, allowed)
        if descriptors is None or not keypoints:
            return Features(np.zeros((0, 2)), np.zeros((0, 32), np.uint8))
        if self._max_features and len(keypoints) > self._max_features:
            order = np.argsort([-k.response for k in keypoints])[:self._max_features]
            keypoints, descriptors = [keypoints[i] for i in order], descriptors[order]
        return Features(cv2.KeyPoint_convert(keypoints).astype(np.float64), descriptors)

    def match(self, feat_a: Features, feat_b: Features) -> PairResult:
        """Ratio-test matching by Hamming distance and a robust motion model (b to a)."""
        return ratio_test_motion(self._matcher, feat_a.points, feat_a.descriptors, feat_b.points,
                                 feat_b.descriptors, self.config)


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``opencv-orb``."""
    return [OpenCVOrbConfig]
