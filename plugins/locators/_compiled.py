"""Compiled kernels of the locators (numba), imported on first use.

:mod:`photonpano.plugins.locators.common` keeps to numpy at module level (listing the
plugins must not load numba); the per-pair arithmetic that runs on the executor's
threads lives here, compiled without the GIL.
"""

from __future__ import annotations

import numpy as np
from photonpano.jit import cached_njit

__all__ = ["capped_transfer_error", "normalised_flux"]


@cached_njit(nogil=True)
def capped_transfer_error(model, src, dst, sigma2, cap):  # pragma: no cover - compiled
    """Sum over points of ``min(|model(src_i) - dst_i|^2 / sigma2, cap)`` (float64; NaN propagates).

    Args:
        model: (3, 3) float64 homography mapping ``src`` to ``dst``.
        src: (N, 2) float32 or float64 points, pixels.
        dst: (N, 2) float32 or float64 points, pixels.
        sigma2: squared noise level, pixels^2.
        cap: largest contribution of one point.
    """
    total = 0.0
    for i in range(len(src)):
        x, y = float(src[i, 0]), float(src[i, 1])
        den = model[2, 0] * x + model[2, 1] * y + model[2, 2]
        u = (model[0, 0] * x + model[0, 1] * y + model[0, 2]) / den - float(dst[i, 0])
        v = (model[1, 0] * x + model[1, 1] * y + model[1, 2]) / den - float(dst[i, 1])
        error = (u * u + v * v) / sigma2
        total += cap if error > cap else error
    return total


@cached_njit(nogil=True)
def normalised_flux(flux, trusted, out):  # pragma: no cover - compiled
    """``out = nan_to_num(flux) / (2 * mean)``, the mean over trusted finite pixels (as is where it is not > 0).

    Args:
        flux: (N,) float32, NaN where unobserved.
        trusted: (N,) bool.
        out: (N,) float32, written.
    """
    top = np.finfo(np.float32).max
    total, count = 0.0, 0
    for i in range(flux.size):
        value = flux[i]
        if np.isnan(value):
            value = np.float32(0.0)
        elif np.isinf(value):
            value = top if value > 0 else -top
        elif trusted[i]:
            total += value
            count += 1
        out[i] = value
    mean = total / count if count else 0.0
    if mean > 0:
        scale = np.float32(2 * mean)
        for i in range(out.size):
            out[i] /= scale
