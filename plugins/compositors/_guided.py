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
   of one canvas pixel): the ratio ``k_c = G * (N_c F_c) / G * (N_c Y_m)`` (``G`` a
   Gaussian of ``sigma_px`` canvas pixels; the maximum-likelihood gain of Poisson
   counts), and the guided estimate ``Q_c = k_c Y``;
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

__all__ = ["guided_colour", "footprint_tent", "CHROMA_SIGMA_PX", "CHROMA_DETAIL_GAIN", "RESIDUAL_SIGMA_PX"]

CHROMA_SIGMA_PX = 1.5
"""Default standard deviation, in canvas pixels at scale 1, of the Gaussian that averages the
colour ratios. Chosen with :data:`CHROMA_DETAIL_GAIN` and :data:`RESIDUAL_SIGMA_PX` on the 15
photos of ``benchmarks/colour.py`` (docs/capture_formats.md). Measured without the fine
step, gain over the per-plane drizzle merge smallest / mean: +2.17 / +3.49, +2.21 / +3.54,
+2.23 / +3.57 dB at 1, 1.5, 2 (residual 1, detail gain 0.5); without the coarse residual
either, 0.7 lost on one photo and 3 gained only +0.6 dB on another."""

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


def guided_colour(luma: NDArray[np.float32], planes: NDArray[np.float32], frames: NDArray[np.float32],
                  exposure_s: float, *, sigma_px: float = CHROMA_SIGMA_PX, residual_px: float = RESIDUAL_SIGMA_PX,
                  sharpness: float = 1.0, binary: bool = True,
                  detail_gain: float = CHROMA_DETAIL_GAIN) -> NDArray[np.float32]:
    """Colour panorama from a sharp luminance and the sparse colour planes (see the module docstring).

    Args:
        luma: (Hc, Wc) float32 luminance flux ``Y`` (any unit: only ratios are used), NaN
            where unobserved: the unfiltered pixels with point drops.
        planes: (Hc, Wc, 3) float32 flux ``F_c`` in photons/s of the R, G, B planes merged
            on their own (square drops of one canvas pixel), NaN where unobserved.
        frames: (Hc, Wc, 3) float32 drop-weighted frames ``N_c`` behind each plane pixel.
        exposure_s: binary frame exposure ``tau`` in seconds.
        sigma_px: standard deviation in canvas pixels of the Gaussian over the ratios.
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
        ValueError: on mismatched shapes or a ``sigma_px``, ``residual_px`` or
            ``exposure_s`` not above 0.
    """
    luma = np.asarray(luma, np.float32)
    if planes.shape != (*luma.shape, 3) or frames.shape != planes.shape:
        raise ValueError(f"guided_colour: expected luma (H, W) and planes, frames (H, W, 3), got {luma.shape}, "
                         f"{planes.shape}, {frames.shape}")
    if not (sigma_px > 0 and residual_px > 0 and exposure_s > 0):
        raise ValueError(f"guided_colour: sigma_px, residual_px and exposure_s must be above 0, got {sigma_px}, "
                         f"{residual_px}, {exposure_s}")
    matched = footprint_tent(luma)
    out = np.empty(planes.shape, np.float32)
    for c in range(3):
        flux, n = planes[..., c], np.asarray(frames[..., c], np.float32)
        seen = np.isfinite(flux) & (n > 0)
        both = seen & np.isfinite(matched)
        w = np.where(both, n, 0).astype(np.float32)
        num = _filter(w * np.where(both, flux, 0), sigma_px)
        den = _filter(w * np.where(both, matched, 0), sigma_px)
        guide = np.where(den > 1e-30, num / np.maximum(den, 1e-30), np.nan) * luma
        # photon noise of the plane, in (photons/s)^2
        n_eff = np.maximum(n, 1e-6) / sharpness
        if binary:
            p = np.clip(1 - np.exp(-np.where(seen, flux, 0) * exposure_s), 0, 0.999)
            noise = p / ((1 - p) * n_eff) / exposure_s ** 2
        else:
            noise = np.where(seen, np.maximum(flux, 0), 0) / (n_eff * exposure_s)
        ok = seen & np.isfinite(guide)
        # the residual, smoothed (frame-weighted), and its noise variance sum(G^2 w^2 var) / (sum G w)^2
        wr = np.where(ok, n, 0).astype(np.float32)
        norm = np.maximum(_filter(wr, residual_px), 1e-6)  # frames: 1e-6 is none
        fine = np.where(ok, flux - guide, 0)
        coarse = _filter(wr * fine, residual_px) / norm
        coarse_noise = (_filter(wr * wr * np.where(ok, noise, 0), residual_px / np.sqrt(2))
                        / (4 * np.pi * residual_px ** 2) / norm ** 2)
        cover = np.maximum(_filter(ok, sigma_px), 1e-12)
        out_c: NDArray[Any] = guide.copy()
        # the coarse residual where its detail beats its noise, then what is left of the
        # plane's own pixels where that beats theirs
        for part, var in ((coarse, coarse_noise), (fine - coarse, np.where(ok, noise, 0))):
            detail = detail_gain * np.maximum(_filter(np.where(ok, part ** 2 - var, 0), sigma_px) / cover, 0)
            out_c = out_c + detail / (detail + var + 1e-30) * part
        out[..., c] = np.where(ok, out_c, np.where(seen, flux, guide))
    return out
