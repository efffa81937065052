"""Luminance-guided colour: sharp luminance from every unfiltered photon, colour ratios where they are sparse.

A colour-filtered SPAD (the SwissSPAD2 colour half array) sees each colour through one
pixel in twelve, at a third of the light: merged on its own, each colour plane
(:class:`~photonpano.plugins.compositors.colour.CfaChannels`) has about 1/36 of the
photons per canvas pixel that the unfiltered pixels give the luminance. Chroma varies
more slowly than luminance in natural scenes, so :func:`guided_colour` takes the detail
from the luminance and only the colour ratios from the planes (the colour-ratio
demosaic of Kimmel, "Demosaicing: image reconstruction from color CCD samples", IEEE TIP
8(9), 1999, and the luminance-guided chroma of joint upsampling, Kopf et al., SIGGRAPH
2007), then blends back the plane where its own colour detail stands above its photon
noise (Lee's local Wiener weight, as noise-adaptive drizzle does, :mod:`._adaptive`):

1. ``Y``: the luminance of every unfiltered pixel, splatted with point drops (sharp:
   it has the photons to afford them) and noise-adaptive (:mod:`._adaptive`);
   ``Y_m = T * Y``, the same blurred by the plane drops' footprint (``T`` the tent
   ``[1/4, 1/2, 1/4]`` per axis: a square drop of one canvas pixel at random sub-pixel
   phase);
2. per channel c with plane flux ``F_c`` and frames ``N_c`` (plain drizzle, square drops
   of one canvas pixel): the ratio ``k = B * (N_c F_c) / B * (N_c Y_m)`` (the
   maximum-likelihood gain of Poisson counts) twice: fine, ``B`` a joint bilateral filter
   (:mod:`._bilateral`: a Gaussian of ``sigma_px`` canvas pixels that does not cross the
   luminance's edges, range ``range_sigma`` in log ``Y_m``), so a colour does not bleed
   across an edge of the luminance; wide, ``B`` a Gaussian of ``wide_px``. The ratio
   ``k_c`` is the wide one plus the fine one's departure from it where that beats its
   noise (Lee's weight, as below): flat regions get the wide ratio's low noise, the
   guided estimate is ``Q_c = k_c Y``;
3. the residual ``R_c = F_c - Q_c`` (the plane's colour detail the ratio misses, plus
   its photon noise) in two steps, each added with Lee's weight ``w = g detail / (g
   detail + noise)`` (``g`` the detail gain, 0.25; the detail is the local mean of the
   step's square above its noise, floored at 0): first ``R_c`` smoothed by a Gaussian of
   ``residual_px`` canvas pixels (frame-weighted), then what is left of the plane's own
   pixels. The noise follows from the plane's binomial noise (``p / ((1 - p) N_eff
   tau^2)``, ``p = 1 - exp(-F_c tau)``; for the smoothed residual ``sum(G^2 w^2 var) /
   (sum G w)^2``). So the plane's colour stays where it beats its noise (a saturated colour
   whose ratio to the luminance changes faster than ``G``), the guide elsewhere.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["guided_colour", "footprint_tent", "CHROMA_SIGMA_PX", "CHROMA_DETAIL_GAIN",
           "RESIDUAL_SIGMA_PX", "WIDE_SIGMA_PX", "RANGE_SIGMA"]

CHROMA_SIGMA_PX = 2.0
"""Default spatial standard deviation, in canvas pixels at scale 1, of the joint bilateral filter
of the fine colour ratio. Measured on the 15 photos of ``benchmarks/colour.py`` (offline, on
each photo's estimated motion; range 0.3, wide ratio 4 px), gain over the per-plane drizzle
merge smallest / mean and mean chroma error: 1.5: +1.55 / +3.72 dB, 1.33 codes; 2: +1.55 /
+3.92, 1.26; 2.5: +1.52 / +4.02, 1.22; 3: +1.48 / +4.07, 1.19 (the cost grows with its
square). Before the bilateral filter and the wide ratio, a Gaussian of 1.5 px: +1.33 / +3.59,
1.37, and objects_coffee's chroma error above the per-plane merge's."""

RESIDUAL_SIGMA_PX = 1.0
"""Default standard deviation, in canvas pixels at scale 1, of the Gaussian over the plane's
residual to the guide (the coarse step). Measured without the fine step (sigma 1.5, detail
gain 0.5), smallest / mean gain: +1.61 / +2.99 dB with no coarse step, +2.08 / +3.30 at 0.7,
+2.21 / +3.54 at 1, +2.26 / +3.68 at 1.5 (where the chroma error on one photo rose above the
per-plane merge's)."""

CHROMA_DETAIL_GAIN = 0.25
"""Default factor on the residuals' detail variance in the blend's weights. With both steps
(sigma 1.5, residual 1): smallest / mean gain +2.21 / +3.41 dB and chroma error 1.22 codes
(mean; at most 2.23) at 0.25, +2.14 / +3.21 dB and 1.26 at 0.5; the fine step keeps a
saturated colour edge of equal luminance (its error 0.065 of full scale against 0.16 with the
coarse step alone and 0.26 with the ratio alone, 400 frames per pixel)."""

WIDE_SIGMA_PX = 4.0
"""Default standard deviation, in canvas pixels at scale 1, of the Gaussian of the wide colour
ratio, which the fine ratio departs from only where the departure beats its noise. Measured as
:data:`CHROMA_SIGMA_PX` (fine 1.5 px, range 0.3): 3 / 4 / 6 px: +1.55 / +3.72, +1.55 / +3.72,
+1.54 / +3.71 dB (interior_clock +3.04); before the wide ratio and the bilateral filter (a
Gaussian ratio of 1.5 px): +1.33 / +3.59 (interior_clock +1.94)."""

RANGE_SIGMA = 0.2
"""Default range standard deviation of the fine ratio's joint bilateral filter, in natural log
of the luminance. Measured as :data:`CHROMA_SIGMA_PX` (fine 2 px, wide 4 px), smallest / mean
gain and mean chroma error: 0.2: +1.57 / +3.87 dB, 1.29 codes; 0.3: +1.55 / +3.92, 1.26 (and
objects_coffee's chroma above the per-plane merge's); at 1.5 px, 0.15 / 0.3 / 0.5: +1.58 /
+3.62, +1.55 / +3.72, +1.47 / +3.76."""

_TENT = np.array([0.25, 0.5, 0.25], np.float32)


def _filter(image: NDArray, kernel: NDArray[np.float32] | float) -> NDArray[np.float32]:
    """Separable filter with zeros outside: ``kernel`` a 1-D array, or a Gaussian's sigma in pixels."""
    import cv2

    image = np.ascontiguousarray(image, np.float32)
    if isinstance(kernel, np.ndarray):
        return np.asarray(cv2.sepFilter2D(image, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_CONSTANT),
                          np.float32)
    return np.asarray(cv2.GaussianBlur(image, (0, 0), float(kernel), borderType=cv2.BORDER_CONSTANT), np.float32)


def footprint_tent(image: NDArray[np.float32]) -> NDArray[np.float32]:
    """``image`` blurred by a one-canvas-pixel square drop's footprint (NaN-aware tent).

    Args:
        image: (Hc, Wc) float32; NaN where unobserved.

    Returns:
        (Hc, Wc) float32: the normalised convolution with ``[1/4, 1/2, 1/4]`` per axis;
        NaN where no observed pixel is within one pixel.
    """
    seen = np.isfinite(image)
    weight = _filter(seen, _TENT)
    out = _filter(np.where(seen, image, 0), _TENT) / np.maximum(weight, 1e-12)
    return np.where(weight > 1e-6, out, np.nan).astype(np.float32)


def _ratio(both: NDArray[np.bool_], weighted: NDArray[np.float32], matched_w: NDArray[np.float32],
           variance: NDArray[np.float32], fine_sums: tuple[NDArray[np.float64], ...], sigma_px: float,
           wide_px: float) -> NDArray[np.float64]:
    """The colour ratio ``k_c`` of one plane (step 2 of the module docstring); NaN where no plane pixel is near.

    ``weighted``, ``matched_w``, ``variance``: ``N_c F_c``, ``N_c Y_m`` and ``N_c^2
    var(F_c)``, zero where unobserved; ``fine_sums``: their joint bilateral sums (the
    first two with the filter's weights, the third with their squares).
    """
    num, den, var_num = fine_sums
    with np.errstate(divide="ignore", invalid="ignore"):
        narrow = np.where(den > 1e-30, num / den, np.nan)
        narrow_var = var_num / den ** 2
        den_wide = _filter(matched_w, wide_px)
        wide = np.where(den_wide > 1e-30, _filter(weighted, wide_px) / den_wide, np.nan)
        wide_var = _filter(variance, wide_px / np.sqrt(2)) / (4 * np.pi * wide_px ** 2) / den_wide ** 2
    # the narrow ratio's departure from the wide one where it beats its noise (Lee's weight)
    both_finite = np.isfinite(narrow) & np.isfinite(wide)
    step = np.where(both_finite, narrow - wide, 0)
    var = np.where(both_finite, np.maximum(narrow_var - wide_var, 0), 0)
    cover = np.maximum(_filter(both, sigma_px), 1e-12)
    detail = np.maximum(_filter(np.where(both, step ** 2 - var, 0), sigma_px) / cover, 0)
    return np.asarray(wide + detail / (detail + var + 1e-30) * step, np.float64)


def guided_colour(luma: NDArray[np.float32], planes: NDArray[np.float32], frames: NDArray[np.float32],
                  exposure_s: float, *, sigma_px: float = CHROMA_SIGMA_PX, residual_px: float = RESIDUAL_SIGMA_PX,
                  wide_px: float = WIDE_SIGMA_PX, range_sigma: float = RANGE_SIGMA, sharpness: float = 1.0,
                  binary: bool = True, detail_gain: float = CHROMA_DETAIL_GAIN) -> NDArray[np.float32]:
    """Colour panorama from a sharp luminance and the sparse colour planes (see the module docstring).

    Args:
        luma: (Hc, Wc) float32 luminance flux ``Y`` (any unit: only ratios are used), NaN
            where unobserved: the unfiltered pixels with point drops.
        planes: (Hc, Wc, 3) float32 flux ``F_c`` in photons/s of the R, G, B planes merged
            on their own (square drops of one canvas pixel), NaN where unobserved.
        frames: (Hc, Wc, 3) float32 drop-weighted frames ``N_c`` behind each plane pixel.
        exposure_s: binary frame exposure ``tau`` in seconds.
        sigma_px: spatial standard deviation in canvas pixels of the joint bilateral
            filter over the ratios (the fine ratio).
        wide_px: standard deviation in canvas pixels of the Gaussian of the wide ratio.
        range_sigma: range standard deviation of the joint bilateral filter, in natural
            log of the luminance (0.2: neighbours 20 % brighter or darker weigh 0.61).
        residual_px: standard deviation in canvas pixels of the Gaussian over the plane's
            residual ``F_c - Q_c`` in the coarse step.
        sharpness: the plane drops' ``sum(w^2) / sum(w)``
            (:func:`._adaptive.drop_sharpness`): ``N_eff = N_c / sharpness``.
        binary: binomial noise of a binary source; False: Poisson counts
            (intensity sources).
        detail_gain: factor on the residuals' detail variance in the blend's weights
            (1: Lee's weight; larger keeps more of the plane).

    Returns:
        (Hc, Wc, 3) float32 flux in photons/s behind the R, G, B filters; the guided
        estimate where the plane is unobserved, the plane where the luminance is; NaN
        where neither is.

    Raises:
        ValueError: on mismatched shapes or a ``sigma_px``, ``residual_px``,
            ``wide_px``, ``range_sigma`` or ``exposure_s`` not above 0.
    """
    luma = np.asarray(luma, np.float32)
    if planes.shape != (*luma.shape, 3) or frames.shape != planes.shape:
        raise ValueError(f"guided_colour: expected luma (H, W) and planes, frames (H, W, 3), got {luma.shape}, "
                         f"{planes.shape}, {frames.shape}")
    if not (sigma_px > 0 and residual_px > 0 and wide_px > 0 and range_sigma > 0 and exposure_s > 0):
        raise ValueError(f"guided_colour: sigma_px, residual_px, wide_px, range_sigma and exposure_s must be above 0, "
                         f"got {sigma_px}, {residual_px}, {wide_px}, {range_sigma}, {exposure_s}")
    from ._bilateral import joint_bilateral_sums

    matched = footprint_tent(luma)
    # the bilateral filter's guide: log luminance, no detection (0) as the faintest one seen
    positive = matched[matched > 0]
    floor = float(positive.min()) if positive.size else 1.0
    with np.errstate(invalid="ignore"):
        log_luma = np.log(np.maximum(matched, floor)).astype(np.float32)  # NaN stays NaN: unobserved
    seen = np.isfinite(planes) & (frames > 0)
    both = seen & np.isfinite(matched)[..., None]
    # photon noise of the planes, in (photons/s)^2
    n_eff = np.maximum(frames, 1e-6) / sharpness
    if binary:
        p = np.clip(1 - np.exp(-np.where(seen, planes, 0) * exposure_s), 0, 0.999)
        noise = p / ((1 - p) * n_eff) / exposure_s ** 2
    else:
        noise = np.where(seen, np.maximum(planes, 0), 0) / (n_eff * exposure_s)
    w = np.where(both, frames, 0).astype(np.float32)
    weighted = np.moveaxis(w * np.where(both, planes, 0), -1, 0)
    matched_w = np.moveaxis(w * np.where(both, matched[..., None], 0), -1, 0)
    variance = np.moveaxis(w * w * np.where(both, noise, 0), -1, 0)
    # one pass of the joint bilateral filter for the three planes (it shares the weights)
    sums, squared_sums = joint_bilateral_sums(np.concatenate([weighted, matched_w]), variance, log_luma, sigma_px,
                                              range_sigma)
    ratios = np.stack([_ratio(both[..., c], weighted[c], matched_w[c], variance[c],
                              (sums[c], sums[3 + c], squared_sums[c]), sigma_px, wide_px)
                       for c in range(3)], -1)
    out = np.empty(planes.shape, np.float32)
    for c in range(3):
        flux, n, seen_c, noise_c = planes[..., c], np.asarray(frames[..., c], np.float32), seen[..., c], noise[..., c]
        guide = ratios[..., c] * luma
        ok = seen_c & np.isfinite(guide)
        # the residual, smoothed (frame-weighted), and its noise variance sum(G^2 w^2 var) / (sum G w)^2
        wr = np.where(ok, n, 0).astype(np.float32)
        norm = np.maximum(_filter(wr, residual_px), 1e-6)  # frames: 1e-6 is none
        fine = np.where(ok, flux - guide, 0)
        coarse = _filter(wr * fine, residual_px) / norm
        coarse_noise = (_filter(wr * wr * np.where(ok, noise_c, 0), residual_px / np.sqrt(2))
                        / (4 * np.pi * residual_px ** 2) / norm ** 2)
        cover = np.maximum(_filter(ok, sigma_px), 1e-12)
        out_c: NDArray[Any] = guide.copy()
        # the coarse residual where its detail beats its noise, then what is left of the
        # plane's own pixels where that beats theirs
        for part, var in ((coarse, coarse_noise), (fine - coarse, np.where(ok, noise_c, 0))):
            detail = detail_gain * np.maximum(_filter(np.where(ok, part ** 2 - var, 0), sigma_px) / cover, 0)
            out_c = out_c + detail / (detail + var + 1e-30) * part
        out[..., c] = np.where(ok, out_c, np.where(seen_c, flux, guide))
    return out

