"""ECC polish of a registration: the normalised flux image, the polish and the corner change it is judged by.

Used by the feature locators' optional polish (``refine: ecc``,
:class:`~photonpano.plugins.locators.common.FeatureLocator`) and by the direct
locators (``opencv-ecc``, ``kornia-direct``). Only numpy at module level; OpenCV is
imported inside functions. Not a plugin (it registers nothing).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["ecc_image", "ecc_polish", "corner_change"]


def ecc_image(flux: NDArray[np.float32], mask: NDArray[np.bool_], exposure_s: float | None = None
              ) -> NDArray[np.float32]:
    """Return a merged frame for ECC: its flux, or with ``exposure_s`` its stabilised detections, scaled near [0, 1].

    With ``exposure_s`` (the merged frames of a binary capture, :attr:`MergedFrames.exposure_s
    <photonpano.records.MergedFrames>`), the flux is first turned into
    :func:`~photonpano.binomial.stabilised_detections`, whose noise is the same at every
    flux, so ECC's least squares weighs each pixel by its information rather than by the
    flux MLE's noise, which grows with the flux (evaluation suite: trajectory RMSE -8 %,
    geometric mean over 48 captures; docs/locators.md). The result is scaled so that twice its mean over the trusted
    pixels is 1 (ECC is invariant to gain and offset; this keeps the numbers near 1).
    Every observed pixel keeps its (possibly noisier) value: zeroing the untrusted border
    would put false edges into the moving image and bias the alignment. Unobserved (NaN)
    pixels are 0.

    Args:
        flux: (H, W) float32 flux in photons/s, NaN where unobserved.
        mask: (H, W) bool trusted pixels, used to pick the white level.
        exposure_s: binary frame exposure in seconds, or None (intensity frames: the flux
            as is).

    Returns:
        (H, W) float32 image.

    Raises:
        ValueError: if ``flux`` and ``mask`` differ in shape.
    """
    from photonpano.binomial import stabilised_detections

    from ._compiled import normalised_flux

    flux, mask = np.ascontiguousarray(flux, np.float32), np.ascontiguousarray(mask, bool)
    if flux.shape != mask.shape:
        raise ValueError(f"ecc_image: flux {flux.shape} and mask {mask.shape} differ in shape")
    if exposure_s is not None:
        flux = stabilised_detections(flux, exposure_s)
    # one compiled pass (runs once per merged frame and panorama view, on the workers)
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
