"""Locator ``opencv-sift``: SIFT features, Lowe's ratio test and a robust homography.

This is the paper's locator (Sec. 5, "Implementation Details": OpenCV SIFT and RANSAC
homography fitting between merged frames). Features are computed once per merged frame
and reused by both pairs the frame belongs to.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from photonpano import hookimpl
from photonpano.stages import LocatorConfig, Locator, MergedFrames, PairRegistrations

ROBUST_METHODS = ("ransac", "usac-magsac", "usac-accurate", "lmeds")


class OpenCVSiftConfig(LocatorConfig):
    """OpenCV SIFT + ratio test + RANSAC/USAC homography between merged frames."""

    plugin: Literal["opencv-sift"] = "opencv-sift"
    max_features: Annotated[int, Field(ge=0)] = 4000
    """Keypoints kept per merged frame, strongest first (0 = all)."""
    contrast_threshold: Annotated[float, Field(gt=0)] = 0.02
    """SIFT contrast threshold (OpenCV's default is 0.04; merged frames are low-contrast)."""
    ratio: Annotated[float, Field(gt=0, lt=1)] = 0.75
    """Lowe ratio-test threshold (dimensionless)."""
    method: Literal["ransac", "usac-magsac", "usac-accurate", "lmeds"] = "usac-magsac"
    """Robust estimator of the homography."""
    reprojection_px: Annotated[float, Field(gt=0)] = 1.5
    """Inlier threshold of the robust estimator, in pixels."""
    min_inliers: Annotated[int, Field(ge=4)] = 20
    """A pair with fewer inliers is flagged as failed (and bridged)."""
    refine: bool = True
    """Refit the homography to all inliers by least squares (Levenberg-Marquardt)."""

    def build(self) -> OpenCVSiftLocator:
        """Return the locator."""
        return OpenCVSiftLocator(self)


class OpenCVSiftLocator(Locator):
    """Registers pairs of merged frames with SIFT (see :class:`OpenCVSiftConfig`)."""

    def __init__(self, config: OpenCVSiftConfig) -> None:
        import cv2

        self.config = config
        self._sift = cv2.SIFT_create(nfeatures=config.max_features,
                                     contrastThreshold=config.contrast_threshold)
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)
        self._method = {"ransac": cv2.RANSAC, "usac-magsac": cv2.USAC_MAGSAC,
                        "usac-accurate": cv2.USAC_ACCURATE, "lmeds": cv2.LMEDS}[config.method]

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

        keep = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8))
        keypoints, descriptors = self._sift.detectAndCompute(image, keep)
        if descriptors is None or not keypoints:
            return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
        return np.float32([k.pt for k in keypoints]), descriptors

    def match(self, feat_a, feat_b) -> tuple[NDArray[np.float64], int, int, bool]:
        """Estimate the homography mapping frame b's pixels to frame a's.

        Returns:
            ``(homography, matches, inliers, ok)``; homography is (3, 3) float64.
        """
        import cv2

        (pts_a, desc_a), (pts_b, desc_b) = feat_a, feat_b
        failed = (np.eye(3), 0, 0, False)
        if len(pts_a) < 4 or len(pts_b) < 4:
            return failed
        pairs = self._matcher.knnMatch(desc_b, desc_a, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < self.config.ratio * p[1].distance]
        if len(good) < max(4, self.config.min_inliers):
            return (np.eye(3), len(good), 0, False)
        src = pts_b[[m.queryIdx for m in good]]
        dst = pts_a[[m.trainIdx for m in good]]
        h, inlier_mask = cv2.findHomography(src, dst, self._method, self.config.reprojection_px,
                                            maxIters=5000, confidence=0.999)
        if h is None or inlier_mask is None:
            return (np.eye(3), len(good), 0, False)
        inl = inlier_mask.ravel().astype(bool)
        n_in = int(inl.sum())
        if self.config.refine and n_in >= 8:
            refined, _ = cv2.findHomography(src[inl], dst[inl], 0)
            if refined is not None:
                h = refined
        ok = n_in >= self.config.min_inliers and abs(np.linalg.det(h[:2, :2])) > 1e-3
        return h / h[2, 2], len(good), n_in, bool(ok)

    def register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64],
                       initial: NDArray[np.float64]) -> PairRegistrations:
        """Register each pair (see :meth:`Locator.register_pairs`); ``initial`` is unused."""
        cache: dict[int, tuple] = {}

        def feats(i: int):
            if i not in cache:
                cache[i] = self.features(merged.images[i], merged.masks[i])
            return cache[i]

        results = [self.match(feats(int(a)), feats(int(b))) for a, b in pairs]
        return PairRegistrations(
            homographies=np.array([r[0] for r in results]).reshape(-1, 3, 3),
            matches=np.array([r[1] for r in results], dtype=np.int64),
            inliers=np.array([r[2] for r in results], dtype=np.int64),
            ok=np.array([r[3] for r in results], dtype=bool),
        )


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``opencv-sift``."""
    return [OpenCVSiftConfig]
