"""Joint (cross) bilateral sums: local weighted sums that do not cross the edges of a guide image.

The joint bilateral filter (Petschnigg et al., "Digital photography with flash and no-flash
image pairs", SIGGRAPH 2004; Eisemann & Durand, same volume; Kopf et al., "Joint bilateral
upsampling", SIGGRAPH 2007) weighs the neighbour at offset ``d`` of pixel ``x`` by a
spatial Gaussian of ``|d|`` times a range Gaussian of the *guide*'s difference
``guide(x + d) - guide(x)``: a sum over a neighbourhood that stays on its own side of
the guide's edges. :func:`joint_bilateral_sums` returns the sums (not the normalised
filter), so callers can form ratios of weighted sums and their noise variances (the
squared weights) from one pass.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from photonpano.jit import cached_njit

__all__ = ["joint_bilateral_sums"]


@cached_njit(nogil=True)
def _sums(values: NDArray[np.float32], squared: NDArray[np.float32], guide: NDArray[np.float32], sigma_px: float,
          range_sigma: float, radius: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover
    k, h, w = values.shape
    m = squared.shape[0]
    out = np.zeros((k, h, w), np.float64)
    out_sq = np.zeros((m, h, w), np.float64)
    inv_r = 1.0 / (2.0 * range_sigma * range_sigma)
    spatial = np.empty((2 * radius + 1, 2 * radius + 1))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            spatial[dy + radius, dx + radius] = math.exp(-(dx * dx + dy * dy) / (2.0 * sigma_px * sigma_px))
    for y in range(h):
        for x in range(w):
            centre = guide[y, x]
            for dy in range(-radius, radius + 1):
                yy = y + dy
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-radius, radius + 1):
                    xx = x + dx
                    if xx < 0 or xx >= w:
                        continue
                    other = guide[yy, xx]
                    if math.isnan(other):
                        continue
                    weight = spatial[dy + radius, dx + radius]
                    if not math.isnan(centre):
                        diff = other - centre
                        weight *= math.exp(-diff * diff * inv_r)
                    for i in range(k):
                        out[i, y, x] += weight * values[i, yy, xx]
                    weight *= weight
                    for i in range(m):
                        out_sq[i, y, x] += weight * squared[i, yy, xx]
    return out, out_sq


def joint_bilateral_sums(values: NDArray, squared: NDArray, guide: NDArray, sigma_px: float,
                         range_sigma: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Joint bilateral sums of ``values`` (weights ``b``) and of ``squared`` (weights ``b**2``).

    ``b(x, d) = exp(-|d|^2 / (2 sigma_px^2)) exp(-(guide(x + d) - guide(x))^2 / (2
    range_sigma^2))`` over offsets ``|dx|, |dy| <= ceil(2 sigma_px)``, zero outside the
    image and at neighbours where ``guide`` is NaN; where ``guide(x)`` itself is NaN the
    range factor is 1 (a plain truncated Gaussian). The ``b**2`` sums give the variance of
    a ``b``-weighted sum of independent terms.

    Args:
        values: (K, H, W) float arrays to sum with weights ``b`` (zeros where unobserved).
        squared: (M, H, W) float arrays to sum with weights ``b**2`` (e.g. weighted
            variances).
        guide: (H, W) float guide, in the unit of ``range_sigma`` (e.g. natural log of a
            luminance); NaN where unobserved.
        sigma_px: spatial standard deviation in pixels (> 0).
        range_sigma: range standard deviation in the guide's unit (> 0).

    Returns:
        ``(sums, squared_sums)``: (K, H, W) and (M, H, W) float64.

    Raises:
        ValueError: on shapes that do not match ``guide`` or a ``sigma_px`` or
            ``range_sigma`` not above 0.
    """
    values = np.ascontiguousarray(values, np.float32)
    squared = np.ascontiguousarray(squared, np.float32)
    guide = np.ascontiguousarray(guide, np.float32)
    if values.ndim != 3 or squared.ndim != 3 or values.shape[1:] != guide.shape or squared.shape[1:] != guide.shape:
        raise ValueError(f"joint_bilateral_sums: expected values (K, H, W) and squared (M, H, W) with guide (H, W), "
                         f"got {values.shape}, {squared.shape}, {guide.shape}")
    if not (sigma_px > 0 and range_sigma > 0):
        raise ValueError(f"joint_bilateral_sums: sigma_px and range_sigma must be above 0, got {sigma_px}, "
                         f"{range_sigma}")
    sums, squared_sums = _sums(values, squared, guide, float(sigma_px), float(range_sigma),
                               int(math.ceil(2 * sigma_px)))
    return sums, squared_sums
