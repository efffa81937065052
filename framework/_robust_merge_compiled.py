"""The robust merge's compiled kernel (numba), imported when first used, not at plugin registration."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .jit import cached_njit

__all__ = ["weighted_median_kernel"]


@cached_njit(nogil=True)
def weighted_median_kernel(values: NDArray[np.float32], weights: NDArray[np.float32],
                           out: NDArray[np.float32]) -> None:  # pragma: no cover - compiled
    """:func:`~photonpano.robust_merge._weighted_median` into ``out``: an insertion sort of each pixel's values.

    Args:
        values: (K, H, W) float32 C-contiguous values (NaN: no weight).
        weights: (K, H, W) float32 C-contiguous weights (>= 0).
        out: (H, W) float32, filled with the first value, in ascending order, at which the
            cumulative weight reaches half the total (NaN where nothing has weight).
    """
    k_count, height, width = values.shape
    sorted_values = np.empty(k_count, np.float32)
    sorted_weights = np.empty(k_count, np.float32)
    for y in range(height):
        for x in range(width):
            n = 0
            for k in range(k_count):
                value, weight = values[k, y, x], weights[k, y, x]
                if not (np.isfinite(value) and weight > 0):
                    continue
                i = n
                while i > 0 and sorted_values[i - 1] > value:
                    sorted_values[i], sorted_weights[i] = sorted_values[i - 1], sorted_weights[i - 1]
                    i -= 1
                sorted_values[i], sorted_weights[i] = value, weight
                n += 1
            total = np.float32(0)
            for i in range(n):
                total += sorted_weights[i]
            if n == 0 or not total > 0:
                out[y, x] = np.nan
                continue
            half, cumulative = np.float32(0.5) * total, np.float32(0)
            pick = n - 1
            for i in range(n):
                cumulative += sorted_weights[i]
                if cumulative >= half:
                    pick = i
                    break
            out[y, x] = sorted_values[pick]
