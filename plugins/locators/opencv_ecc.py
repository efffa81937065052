"""Locator ``opencv-ecc``: direct (intensity-based) homography by ECC over an image pyramid.

No features: each pair's homography maximises the enhanced correlation coefficient
(Evangelidis and Psarakis, 2008) between the two merged flux images, starting from the
framework's current estimate (``initial``) and refined coarse to fine over a pyramid of
2x area-averaged images, with OpenCV's ``findTransformECCWithMask`` at each scale (both
frames' trusted-pixel masks are honoured). Sub-pixel by construction.

Why not ``cv2.findTransformECCMultiScale``: in OpenCV 5.0.0 it fails with "NaN
encountered" whenever masks are given and more than one pyramid level is used, and
merged frames need masks (their borders are unobserved). The pyramid here is explicit,
with the pixel-centre convention handled exactly: a 2x area reduction maps pixel
``x`` to ``(x + 0.5) / 2 - 0.5``.

A pair fails (``ok=False``) when ECC does not converge, when the final correlation is
below ``min_correlation``, when the result moves a frame corner more than
``max_change_px`` from the initial estimate, or when too little of frame b lands in
frame a. ``matches`` is 0 and ``inliers`` is the number of trusted pixels of frame b
that land on trusted pixels of frame a (its weight in the framework's pose graph).
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.stages import LocatorConfig
from pydantic import Field

from .common import DirectLocator, PairResult
from .polish import corner_change, ecc_image

__all__ = ["OpenCVEccConfig", "OpenCVEccLocator", "ecc_pyramid", "pyramid_homography"]


class OpenCVEccConfig(LocatorConfig):
    """Direct homography by ECC maximisation over an image pyramid, from the current estimate."""

    plugin: Literal["opencv-ecc"] = "opencv-ecc"
    template_defaults: ClassVar[dict[str, Any]] = {"pyramid_levels": 1, "finest_level": 0, "iterations": 10,
                                                   "epsilon": 1e-4, "blur": 5}
    """Against the panorama (the ``mosaic`` scheme) the residual motion is about a pixel, so
    one pyramid level and a few iterations suffice; with the default ``registration_binning:
    2`` the merged frames are already at half resolution, which is enough against a
    low-noise template (0.14 vs 0.13 px trajectory RMSE at 100k frames for 2.5x less ECC
    time, measured when ECC itself stopped at half resolution). ``epsilon: 1e-4`` stops
    after two or three iterations: over 300 level-3 registrations of the benchmark's pan
    the result moved a corner 0.007 px (95th percentile) from that of ``1e-5``, for 17 %
    less ECC time; trajectory RMSE unchanged (0.0805 vs 0.0804 px)."""
    pyramid_levels: Annotated[int, Field(ge=1, le=6)] = 3
    """Pyramid levels (1 = full resolution only); each level halves the image, so the
    coarsest level tolerates an initial error of about 2**(levels-1) times a few pixels."""
    finest_level: Annotated[int, Field(ge=0, le=5)] = 0
    """Pyramid level where the coarse-to-fine refinement stops (0 = full resolution;
    1 = half resolution, about 4x cheaper, enough against a low-noise template)."""
    iterations: Annotated[int, Field(gt=0)] = 50
    """Maximum ECC (Gauss-Newton) iterations per pyramid level."""
    epsilon: Annotated[float, Field(gt=0)] = 1e-5
    """Stop a level when the correlation coefficient improves by less than this."""
    blur: Annotated[int, Field(ge=1, le=15)] = 5
    """Size of ECC's Gaussian pre-filter in pixels at each level (odd, 1 = none)."""
    motion: Literal["homography", "affine", "euclidean", "translation"] = "homography"
    """Motion model fitted by ECC (the result is always returned as a 3x3 homography)."""
    min_correlation: Annotated[float, Field(ge=-1, le=1)] = 0.3
    """A pair whose final correlation coefficient is below this is flagged as failed."""
    max_change_px: Annotated[float, Field(gt=0)] = 40.0
    """A result that moves a frame corner further than this (pixels) from the initial
    estimate is flagged as failed (a divergence)."""
    min_overlap: Annotated[float, Field(gt=0, le=1)] = 0.2
    """Fraction of frame b's trusted pixels that must land on trusted pixels of frame a."""

    def converging(self) -> OpenCVEccConfig:
        """This config with at least 10 iterations per level and ``epsilon`` at most 1e-8 (see the base).

        ECC stops when the correlation coefficient improves by less than ``epsilon``, and
        two frames that overlap by 70 % converge slowly in their shape (rotation,
        keystone): the long chains' links of the suite's brick facade at flux 0.05
        (2026-11-27, 19 links) stopped at ``template_defaults``' ``epsilon`` 1e-4 a median
        0.009 px and a 90th percentile 0.067 px (binned pixels) short of where 300
        iterations end, always on the side of the start, i.e. of the current estimate; 10
        iterations leave 0.008 px, 20 0.0001 px. Registrations against the panorama
        converge in two (0.0003 px).
        """
        return self.model_copy(update={"iterations": max(self.iterations, 10), "epsilon": min(self.epsilon, 1e-8)})

    def build(self) -> OpenCVEccLocator:
        """Return the locator."""
        return OpenCVEccLocator(self)


def ecc_pyramid(image: NDArray[np.float32], mask: NDArray[np.bool_], levels: int
                ) -> list[tuple[NDArray[np.float32], NDArray[np.uint8]]]:
    """Build a 2x area-averaged pyramid of an image and its validity mask.

    Args:
        image: (H, W) float32 image.
        mask: (H, W) bool valid pixels.
        levels: number of levels (the first is the input).

    Returns:
        ``levels`` pairs ``(image, mask)`` from fine to coarse: (H_k, W_k) float32 and
        uint8 (1 where every input pixel under the coarse pixel was valid). Level k
        pixel ``x_k`` is at ``(x + 0.5) / 2**k - 0.5`` in input pixels ``x``.
    """
    import cv2

    out = [(np.ascontiguousarray(image, np.float32), mask.astype(np.uint8))]
    for _ in range(levels - 1):
        img, msk = out[-1]
        h, w = img.shape
        if min(h, w) < 16:
            break
        size = (w // 2, h // 2)
        # crop to even size so that the 2x2 blocks (and the pixel-centre map) are exact
        img, msk = img[:2 * size[1], :2 * size[0]], msk[:2 * size[1], :2 * size[0]]
        small = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        valid = cv2.resize(msk.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
        out.append((small, valid.astype(np.uint8)))
    return out


def pyramid_homography(homography: NDArray[np.float64], level: int) -> NDArray[np.float64]:
    """Express a full-resolution homography in the pixels of pyramid ``level``.

    Args:
        homography: (3, 3) float64 in full-resolution pixels.
        level: pyramid level (0 = full resolution; each level halves; a negative level
            maps back from level ``-level`` to full resolution).

    Returns:
        (3, 3) float64 ``S @ H @ inv(S)`` with ``S`` the map ``x -> (x + 0.5) / 2**level - 0.5``.
    """
    from photonpano import geometry

    if level == 0:  # S is the identity (and this the common case: one level, at every registration)
        return homography / homography[2, 2]
    s = geometry.scale_matrix(0.5 ** level)
    out = s @ homography @ np.linalg.inv(s)
    return out / out[2, 2]


class OpenCVEccLocator(DirectLocator):
    """Registers pairs by pyramid ECC (see :class:`OpenCVEccConfig`).

    Each frame's normalised flux pyramid is built once per distinct frame content
    (:meth:`cache_stats`).
    """

    prepared_kind = "pyramid"

    def __init__(self, config: OpenCVEccConfig) -> None:
        import cv2

        super().__init__()
        self.config = config
        self._motion = {"homography": cv2.MOTION_HOMOGRAPHY, "affine": cv2.MOTION_AFFINE,
                        "euclidean": cv2.MOTION_EUCLIDEAN,
                        "translation": cv2.MOTION_TRANSLATION}[config.motion]

    def prepare(self, flux: NDArray[np.float32], mask: NDArray[np.bool_]):
        """Return the :func:`ecc_pyramid` of a merged frame's :func:`ecc_image` (stabilised for binary frames)."""
        return ecc_pyramid(ecc_image(flux, mask, self.exposure_s), mask, self.config.pyramid_levels)

    def register(self, pyramid_a, pyramid_b, initial: NDArray[np.float64]) -> PairResult:
        """Register one pair coarse to fine.

        Args:
            pyramid_a: :func:`ecc_pyramid` of frame a (the moving image).
            pyramid_b: :func:`ecc_pyramid` of frame b (the template).
            initial: (3, 3) float64 starting homography mapping b's pixels to a's.

        Returns:
            The pair's result (failures flagged, never raised).
        """
        import cv2

        cfg = self.config
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.iterations, cfg.epsilon)
        initial = initial / initial[2, 2]
        h = initial
        cc = -1.0
        for level in range(len(pyramid_b) - 1, min(cfg.finest_level, len(pyramid_b) - 1) - 1, -1):
            (img_a, msk_a), (img_b, msk_b) = pyramid_a[level], pyramid_b[level]
            warp = pyramid_homography(h, level).astype(np.float32)
            if self._motion != cv2.MOTION_HOMOGRAPHY:
                warp = warp[:2]
            try:
                cc, warp = cv2.findTransformECCWithMask(img_b, img_a, msk_b, msk_a, warp, self._motion,
                                                        criteria, cfg.blur | 1)
            except cv2.error:  # did not converge, or too little overlap
                return PairResult(initial)
            full = np.eye(3)
            full[:warp.shape[0]] = warp
            if not np.isfinite(full).all() or abs(full[2, 2]) < 1e-12:
                return PairResult(initial)
            h = pyramid_homography(full, -level)
        height, width = pyramid_b[0][0].shape
        overlap = self._overlap(pyramid_a[0][1], pyramid_b[0][1], h)
        trusted_b = int(np.count_nonzero(pyramid_b[0][1]))
        ok = (cc >= cfg.min_correlation and corner_change(h, initial, width, height) <= cfg.max_change_px
              and overlap >= cfg.min_overlap * max(trusted_b, 1))
        return PairResult(h, 0, overlap, bool(ok))

    @staticmethod
    def _overlap(mask_a: NDArray[np.uint8], mask_b: NDArray[np.uint8], h: NDArray[np.float64]) -> int:
        """Count trusted pixels of b whose image under ``h`` is a trusted pixel of a."""
        import cv2

        rows, cols = mask_b.shape
        pulled = cv2.warpPerspective(mask_a, h, (cols, rows), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return int(np.count_nonzero(pulled & mask_b))


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``opencv-ecc``."""
    return [OpenCVEccConfig]
