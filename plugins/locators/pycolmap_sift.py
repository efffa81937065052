"""Locator ``pycolmap-sift``: COLMAP's SIFT extraction and matching, COLMAP's LO-RANSAC homography.

Each merged frame is described once (cached by content) with COLMAP's SIFT
(``pycolmap.FeatureExtractor``, VLFeat-style SIFT with RootSIFT normalisation), pairs are
matched with ``pycolmap.FeatureMatcher`` (ratio test, distance threshold and cross check)
and the homography is fitted with ``pycolmap.estimate_homography_matrix`` (LO-RANSAC),
then refitted by least squares to all of its inliers (``refine: lm`` or ``ecc``; on
low-light merged frames COLMAP's own estimate is about twice as far from the truth as
the refit) and optionally polished by ECC like the OpenCV feature locators.

**Pixel convention.** COLMAP puts the image origin at the top-left *corner*, so the
centre of the top-left pixel is ``(0.5, 0.5)``; photonpano (like OpenCV and kornia) puts
it at ``(0, 0)``. Keypoints are converted on the way in (``x - 0.5``), so every
homography this plugin returns is in photonpano's convention; :func:`from_colmap`
converts a homography estimated on raw COLMAP coordinates. (Measured: matching COLMAP
keypoints of an image and of its exact 2x enlargement gives ``x_big = 2 x + 0.5``, the
corner-origin relation, where centre-origin keypoints give ``2 x + 0.5`` only after the
conversion; see ``tests/plugins/locators/test_backends.py``.)

Needs the optional ``colmap`` extra (``pip install 'photonpano[colmap]'``).
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.stages import LocatorConfig
from pydantic import Field

from .common import FeatureLocator, Features, PairResult, PolishConfig, keypoint_mask

__all__ = ["PycolmapSiftConfig", "PycolmapSiftLocator", "COLMAP_OFFSET_PX", "from_colmap", "to_colmap"]

COLMAP_OFFSET_PX = 0.5
"""COLMAP pixel coordinates minus photonpano pixel coordinates of the same point."""


class PycolmapSiftConfig(PolishConfig):
    """pycolmap SIFT extraction + matching + LO-RANSAC homography (estimate_homography_matrix)."""

    plugin: Literal["pycolmap-sift"] = "pycolmap-sift"
    requires: ClassVar[tuple[str, ...]] = ("pycolmap",)
    install_hint: ClassVar[str] = "pip install 'photonpano[colmap]'"

    max_features: Annotated[int, Field(gt=0)] = 4000
    """Keypoints kept per merged frame (COLMAP's ``max_num_features``)."""
    peak_threshold: Annotated[float, Field(gt=0)] = 0.004
    """SIFT peak (contrast) threshold (COLMAP's default is 0.0067; merged frames are low-contrast)."""
    first_octave: Literal[-1, 0] = -1
    """First octave of the scale space: -1 upsamples the image first (COLMAP's default;
    finds more, finer keypoints, which on noisy merged frames are mostly photon noise)."""
    ratio: Annotated[float, Field(gt=0, le=1)] = 0.8
    """Lowe ratio-test threshold of COLMAP's matcher (``max_ratio``)."""
    max_distance: Annotated[float, Field(gt=0, le=1)] = 0.7
    """Largest descriptor distance of a match (COLMAP's ``max_distance``, unit-norm descriptors)."""
    reprojection_px: Annotated[float, Field(gt=0)] = 3.0
    """LO-RANSAC inlier threshold (``max_error``), in pixels (COLMAP's default is 4)."""
    min_inliers: Annotated[int, Field(ge=4)] = 12
    """A pair with fewer inliers is flagged as failed (and bridged)."""
    border_px: Annotated[int, Field(ge=0)] = 8
    """Keypoints closer than this (pixels) to untrusted pixels are dropped."""
    seed: int = 0
    """Seed of LO-RANSAC's sampling (runs are repeatable; -1 = random)."""

    def build(self) -> PycolmapSiftLocator:
        """Return the locator (imports pycolmap).

        Raises:
            MissingDependency: if pycolmap is not installed.
        """
        self.check_available()
        return PycolmapSiftLocator(self)


def to_colmap(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Convert (N, 2) photonpano pixel coordinates to COLMAP's (corner origin): ``+0.5``."""
    return np.asarray(points, np.float64) + COLMAP_OFFSET_PX


def from_colmap(homography: NDArray[np.float64]) -> NDArray[np.float64]:
    """Convert a homography between COLMAP pixel coordinates to photonpano's.

    Args:
        homography: (3, 3) mapping COLMAP coordinates of one image to COLMAP coordinates
            of another.

    Returns:
        (3, 3) float64 ``T(-0.5) @ H @ T(+0.5)``, normalised, acting on photonpano pixels.
    """
    from photonpano import geometry

    h = geometry.translation(-COLMAP_OFFSET_PX, -COLMAP_OFFSET_PX) @ np.asarray(homography, np.float64) \
        @ geometry.translation(COLMAP_OFFSET_PX, COLMAP_OFFSET_PX)
    return h / h[2, 2]


class PycolmapSiftLocator(FeatureLocator):
    """Registers pairs with pycolmap (see :class:`PycolmapSiftConfig`)."""

    thread_safe = False  # one extractor object per locator (torch / COLMAP state)

    def __init__(self, config: PycolmapSiftConfig) -> None:
        import pycolmap

        super().__init__(config)
        self._pycolmap = pycolmap
        pycolmap.logging.minloglevel = 2  # no INFO lines per extractor/matcher on stderr
        sift = {"max_num_features": config.max_features, "peak_threshold": config.peak_threshold,
                "first_octave": config.first_octave}
        extraction = pycolmap.FeatureExtractionOptions(num_threads=1, use_gpu=False)
        extraction.sift.mergedict(sift)
        self._extractor = pycolmap.FeatureExtractor.create(extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions(num_threads=1, use_gpu=False)
        matching.sift.mergedict({"max_ratio": config.ratio, "max_distance": config.max_distance,
                                 "cross_check": True})
        self._matcher = pycolmap.FeatureMatcher.create(matching, device=pycolmap.Device.cpu)
        self._ransac = pycolmap.RANSACOptions(max_error=config.reprojection_px, random_seed=config.seed,
                                              confidence=0.9999, num_threads=1)

    def describe(self, image: NDArray[np.uint8], mask: NDArray[np.bool_],
                 flux: NDArray[np.float32]) -> Features:
        """Extract COLMAP SIFT features (see :meth:`FeatureLocator.describe`).

        Returns:
            Features with (K, 2) float64 points in photonpano's convention (COLMAP's
            minus 0.5) and (K, 128) uint8 descriptors; ``native`` holds COLMAP's
            descriptor object.
        """
        pycolmap = self._pycolmap
        keypoints, descriptors = self._extractor.extract_from_uint8_array(np.ascontiguousarray(image))
        colmap_xy = np.array([[k.x, k.y] for k in keypoints], np.float64).reshape(-1, 2)
        points = colmap_xy - COLMAP_OFFSET_PX
        data = np.asarray(descriptors.data)
        if len(points):
            allowed = keypoint_mask(mask, self.config.border_px)
            col = np.clip(np.rint(points[:, 0]).astype(int), 0, image.shape[1] - 1)
            row = np.clip(np.rint(points[:, 1]).astype(int), 0, image.shape[0] - 1)
            keep = allowed[row, col].astype(bool)
            points, data = points[keep], np.ascontiguousarray(data[keep])
        native = pycolmap.FeatureDescriptors(descriptors.type, data)
        return Features(points, data, native=native)

    def match(self, feat_a: Features, feat_b: Features) -> PairResult:
        """COLMAP matching and LO-RANSAC homography (b to a)."""
        cfg = self.config
        if len(feat_a) < 4 or len(feat_b) < 4:
            return PairResult()
        empty = self._pycolmap.FeatureKeypoints()
        idx = np.asarray(self._matcher.match(empty, feat_b.native, empty, feat_a.native), np.int64)
        idx = idx.reshape(-1, 2)
        n = len(idx)
        if n < max(4, cfg.min_inliers):
            return PairResult(matches=n)
        # estimate in COLMAP's own coordinates, then convert the homography
        src, dst = to_colmap(feat_b.points[idx[:, 0]]), to_colmap(feat_a.points[idx[:, 1]])
        result = self._pycolmap.estimate_homography_matrix(src, dst, self._ransac)
        if result is None:
            return PairResult(matches=n)
        n_in = int(result["num_inliers"])
        h = from_colmap(np.asarray(result["H"], np.float64))
        inliers = np.asarray(result.get("inlier_mask", np.zeros(0)), bool).ravel()
        if cfg.refine != "none" and len(inliers) == n and inliers.sum() >= 8:
            # least-squares refit to all of COLMAP's inliers (in photonpano's coordinates)
            import cv2

            refit, _ = cv2.findHomography(feat_b.points[idx[inliers, 0]].astype(np.float32),
                                          feat_a.points[idx[inliers, 1]].astype(np.float32), 0)
            if refit is not None and np.all(np.isfinite(refit)) and abs(refit[2, 2]) > 1e-12:
                h = refit / refit[2, 2]
        ok = np.all(np.isfinite(h)) and n_in >= cfg.min_inliers and abs(np.linalg.det(h[:2, :2])) > 1e-3
        return PairResult(h if ok else np.eye(3), n, n_in, bool(ok))


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``pycolmap-sift``."""
    return [PycolmapSiftConfig]
