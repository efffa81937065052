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
    min_inliers: Annotated[int, Field(ge=4)] = 12
    """A pair with fewer inliers is flagged as failed (and bridged)."""
    refine: Literal["none", "lm", "ecc"] = "ecc"
    """Polish of the robust estimate: ``lm`` refits it to all inliers by least squares
    (Levenberg-Marquardt, the paper's setting); ``ecc`` then maximises the enhanced
    correlation coefficient between the two merged flux images (Evangelidis and Psarakis,
    2008), a dense sub-pixel refinement that keeps the feature result if it fails."""
    ecc_iterations: Annotated[int, Field(gt=0)] = 30
    """ecc: maximum Gauss-Newton iterations per pair."""
    ecc_blur: Annotated[int, Field(ge=1, le=15)] = 5
    """ecc: size of the Gaussian pre-filter in pixels (odd, 1 = none); merged frames are noisy."""
    ecc_max_change_px: Annotated[float, Field(gt=0)] = 2.0
    """ecc: a refinement that moves a frame corner further than this (pixels) from the
    feature estimate is discarded as a divergence."""

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
        if self.config.refine != "none" and n_in >= 8:
            refined, _ = cv2.findHomography(src[inl], dst[inl], 0)
            if refined is not None:
                h = refined
        ok = n_in >= self.config.min_inliers and abs(np.linalg.det(h[:2, :2])) > 1e-3
        return h / h[2, 2], len(good), n_in, bool(ok)

    def refine_ecc(self, image_a: NDArray[np.float32], image_b: NDArray[np.float32],
                   mask_b: NDArray[np.bool_], homography: NDArray[np.float64]) -> NDArray[np.float64]:
        """Polish a homography (b to a) by ECC maximisation; return the input on failure.

        Args:
            image_a: (H, W) float32 normalised flux of frame a (the moving image).
            image_b: (H, W) float32 normalised flux of frame b (the template).
            mask_b: (H, W) bool pixels of frame b to use.
            homography: (3, 3) float64 starting estimate mapping b's pixels to a's.

        Returns:
            (3, 3) float64 refined homography, or ``homography`` if ECC fails or moves
            a corner by more than ``ecc_max_change_px``.
        """
        import cv2

        from photonpano import geometry

        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.config.ecc_iterations, 1e-5)
        try:
            _, warp = cv2.findTransformECC(image_b, image_a, homography.astype(np.float32),
                                           cv2.MOTION_HOMOGRAPHY, criteria, mask_b.astype(np.uint8),
                                           self.config.ecc_blur | 1)
        except cv2.error:  # did not converge
            return homography
        warp = warp.astype(np.float64) / warp[2, 2]
        h, w = image_b.shape
        corners = geometry.corners(w, h)
        change = np.abs(geometry.apply(warp, corners) - geometry.apply(homography, corners)).max()
        return warp if np.isfinite(change) and change < self.config.ecc_max_change_px else homography

    def register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64],
                       initial: NDArray[np.float64]) -> PairRegistrations:
        """Register each pair (see :meth:`Locator.register_pairs`); ``initial`` is unused."""
        cache: dict[int, tuple] = {}

        def feats(i: int):
            if i not in cache:
                cache[i] = self.features(merged.images[i], merged.masks[i])
            return cache[i]

        results = [self.match(feats(int(a)), feats(int(b))) for a, b in pairs]
        if self.config.refine == "ecc":
            images: dict[int, NDArray[np.float32]] = {}
            for p, (a, b) in enumerate(pairs):
                if results[p][3]:
                    for i in (int(a), int(b)):
                        if i not in images:
                            images[i] = ecc_image(merged.flux[i], merged.masks[i])
                    refined = self.refine_ecc(images[int(a)], images[int(b)], merged.masks[int(b)], results[p][0])
                    results[p] = (refined, *results[p][1:])
        return PairRegistrations(
            homographies=np.array([r[0] for r in results]).reshape(-1, 3, 3),
            matches=np.array([r[1] for r in results], dtype=np.int64),
            inliers=np.array([r[2] for r in results], dtype=np.int64),
            ok=np.array([r[3] for r in results], dtype=bool),
        )


def ecc_image(flux: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Return a merged flux image scaled to about [0, 1] for ECC.

    Every observed pixel keeps its (possibly noisier) flux: zeroing the untrusted border
    would put false edges into the moving image and bias the alignment. Unobserved
    (NaN) pixels are 0.

    Args:
        flux: (H, W) float32 flux, NaN where unobserved.
        mask: (H, W) bool trusted pixels, used to pick the white level.

    Returns:
        (H, W) float32 image.
    """
    trusted = mask & np.isfinite(flux)
    white = float(np.percentile(flux[trusted], 99)) if trusted.any() else 1.0
    return (np.nan_to_num(flux, nan=0.0) / (white if white > 0 else 1.0)).astype(np.float32)


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``opencv-sift``."""
    return [OpenCVSiftConfig]
