"""The compiled kernel of :func:`photonpano.binomial.stabilised_detections`, imported on first use.

``arcsin(sqrt(1 - exp(-x)))`` costs two scalar transcendental calls per pixel in numpy
(float32 ``expm1`` and ``arcsin`` have no SIMD loop on AVX2: 3.3 ms per 254 x 496 frame,
4.8 s of CPU in a 100 000-frame run, where every mosaic level stabilises each merged
frame and its panorama view). As a function of ``s = sqrt(x)`` the transform is smooth
(``g(s) = arcsin(sqrt(1 - exp(-s^2)))``, ``g(s) ~ s`` near 0, ``pi/2`` to float32 beyond
``s = 6``), so a table of ``g`` on 8 192 intervals of ``s`` in [0, 6], linearly
interpolated, is within 3.5e-8 of it everywhere (under half a float32 step at pi/2).
"""

from __future__ import annotations

import numpy as np

from .jit import cached_njit

__all__ = ["TABLE_INTERVALS", "TABLE_END", "transform_table", "stabilise_kernel"]

TABLE_INTERVALS = 8192
"""Intervals of the table of ``g(s)``."""

TABLE_END = 6.0
"""Largest ``s = sqrt(flux * tau)`` in the table; beyond, ``g`` is pi/2 to float32 (``pi/2 - g(6) = 1.5e-8``)."""


def transform_table() -> np.ndarray:
    """(TABLE_INTERVALS + 1,) float64 ``g(s)`` at ``s = k * TABLE_END / TABLE_INTERVALS``."""
    s = np.arange(TABLE_INTERVALS + 1, dtype=np.float64) * (TABLE_END / TABLE_INTERVALS)
    return np.arcsin(np.sqrt(-np.expm1(-s * s)))


@cached_njit(nogil=True)
def stabilise_kernel(flux, tau, table, per_step, out):  # pragma: no cover - compiled
    """``out = g(sqrt(max(flux, 0) * tau))`` by the table (pi/2 beyond it), NaN where ``flux`` is not finite.

    Args:
        flux: (N,) float32 flux in photons/s.
        tau: float32 binary frame exposure in seconds.
        table: :func:`transform_table`.
        per_step: ``TABLE_INTERVALS / TABLE_END`` (table entries per unit of ``s``).
        out: (N,) float32, written.
    """
    last = len(table) - 1
    for i in range(flux.size):
        value = flux[i]
        if not np.isfinite(value):
            out[i] = np.nan
            continue
        x = max(value, np.float32(0.0)) * tau  # float32, as the numpy form
        position = np.sqrt(np.float64(x)) * per_step
        if position >= last:
            out[i] = np.pi / 2
            continue
        k = int(position)
        fraction = position - k
        out[i] = table[k] + fraction * (table[k + 1] - table[k])
