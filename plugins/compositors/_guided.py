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
3. the noise variance of ``F_c`` is binomial (``p / ((1 - p) N_eff tau^2)``, ``p = 1 -
   exp(-F_c tau)``); the plane's own colour detail is the local mean of ``(F_c -
   Q_c)^2`` above that noise (floored at 0); the output is ``Q_c + w (F_c - Q_c)`` with
   ``w = g detail / (g detail + noise)`` (``g`` the detail gain, 0.5): the plane where it is better than the guide (a
   saturated colour whose ratio to the luminance changes faster than ``G``), the guide
   elsewhere.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["guided_colour", "footprint_tent", "CHROMA_SIGMA_PX", "CHROMA_DETAIL_GAIN"]

CHROMA_SIGMA_PX = 1.5
"""Default standard deviation, in canvas pixels at scale 1, of the Gaussian that averages the
colour ratios. Chosen with :data:`CHROMA_DETAIL_GAIN` on the 15 photos of
``benchmarks/colour.py`` (docs/capture_formats.md): the smallest gain over the per-plane
drizzle merge was +1.62 / +1.61 / +1.42 dB at 1.25 / 1.5 / 1.75 (detail gain 0.5), the
mean +2.86 / +2.99 / +3.05 dB; 0.7 lost on one photo, 3 gained only +0.6 dB on another."""

CHROMA_DETAIL_GAIN = 0.5
"""Default factor on the plane's colour detail in the blend's weight (measured with
:data:`CHROMA_SIGMA_PX` 1.5: smallest / mean gain +1.64 / +3.19 dB at 0.3, +1.61 / +2.99 at
0.5, +1.24 / +2.63 at 1; chroma error below the per-plane merge's on every photo from 0.5 up)."""

_TENT = np.array([0.25, 0.5, 0.25], np.float32)


def _filter(image: NDArray, kernel: NDArray[np.float32] | float) -> NDArray[np.float32]:
    """Separable filter with zeros outside: ``kernel`` a 1-D array, or a Gaussian's sigma in pixels."""
    import cv2

    image = np.ascontiguousarray(image, np.float32)
    if isinstance(kernel, np.ndarray):
        return cv2.sepFilter2D(image, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_CONSTANT)
    return cv2.GaussianBlur(image, (0, 0), float(kernel), borderType=cv2.BORDER_CONSTANT)


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
                  exposure_s: float, *, sigma_px: float = CHROMA_SIGMA_PX, sharpness: float = 1.0,
                  binary: bool = True, detail_gain: float = CHROMA_DETAIL_GAIN) -> NDArray[np.float32]:
    """Colour panorama from a sharp luminance and the sparse colour planes (see the module docstring).

    Args:
        luma: (Hc, Wc) float32 luminance flux ``Y`` (any unit: only ratios are used), NaN
            where unobserved: the unfiltered pixels with point drops.
        planes: (Hc, Wc, 3) float32 flux ``F_c`` in photons/s of the R, G, B planes merged
            on their own (square drops of one canvas pixel), NaN where unobserved.
        frames: (Hc, Wc, 3) float32 drop-weighted frames ``N_c`` behind each plane pixel.
        exposure_s: binary frame exposure ``tau`` in seconds.
        sigma_px: standard deviation in canvas pixels of the Gaussian over the ratios.
        sharpness: the plane drops' ``sum(w^2) / sum(w)``
            (:func:`._adaptive.drop_sharpness`): ``N_eff = N_c / sharpness``.
        binary: binomial noise of a binary source; False: Poisson counts
            (intensity sources).
        detail_gain: factor on the plane's colour detail variance in the blend's weight
            (1: Lee's weight; larger keeps more of the plane).

    Returns:
        (Hc, Wc, 3) float32 flux in photons/s behind the R, G, B filters; the guided
        estimate where the plane is unobserved, the plane where the luminance is; NaN
        where neither is.

    Raises:
        ValueError: on mismatched shapes or a ``sigma_px`` or ``exposure_s`` not above 0.
    """
    luma = np.asarray(luma, np.float32)
    if planes.shape != (*luma.shape, 3) or frames.shape != planes.shape:
        raise ValueError(f"guided_colour: expected luma (H, W) and planes, frames (H, W, 3), got {luma.shape}, "
                         f"{planes.shape}, {frames.shape}")
    if not (sigma_px > 0 and exposure_s > 0):
        raise ValueError(f"guided_colour: sigma_px and exposure_s must be above 0, got {sigma_px}, {exposure_s}")
    matched = footprint_tent(luma)
    out = np.empty(planes.shape, np.float32)
    for c in range(3):
        flux, n = planes[..., c], np.asarray(frames[..., c], np.float32)
        seen = np.isfinite(flux) & (n > 0)
        both = seen & np.isfinite(matched)
        w = np.where(both, n, 0).astype(np.float32)
        num = _filter(w * np.where(both, flux, 0), sigma_px)
        den = _filter(w * np.where(both, matched, 0), sigma_px)
        ratio = np.where(den > 1e-30, num / np.maximum(den, 1e-30), np.nan)
        guide = ratio * luma
        # photon noise of the plane, in (photons/s)^2
        n_eff = np.maximum(n, 1e-6) / sharpness
        if binary:
            p = np.clip(1 - np.exp(-np.where(seen, flux, 0) * exposure_s), 0, 0.999)
            noise = p / ((1 - p) * n_eff) / exposure_s ** 2
        else:
            noise = np.where(seen, np.maximum(flux, 0), 0) / (n_eff * exposure_s)
        ok = seen & np.isfinite(guide)
        cover = np.maximum(_filter(ok, sigma_px), 1e-12)
        mismatch = _filter(np.where(ok, (flux - guide) ** 2, 0), sigma_px) / cover
        detail = detail_gain * np.maximum(mismatch - _filter(np.where(ok, noise, 0), sigma_px) / cover, 0)
        keep = detail / (detail + noise + 1e-30)
        blended = guide + keep * (flux - guide)
        out[..., c] = np.where(ok, blended, np.where(seen, flux, guide))
    return out
