"""Compiled kernels of :mod:`photonpano.schemes.template_bias` (numba), imported on first use.

Both loop over (frame, canvas cell) pairs: for each, where the frame sees the cell, the
canvas displacement per unit of the frame's 8 parameters ``D = A(x) J(x - c)`` (``A`` the
Jacobian of the frame-to-canvas homography at the frame pixel ``x`` of the cell, ``J``
the Jacobian of paper Eq. 4's homography at the identity, about the frame centre ``c``), summed
straight into what the model needs instead of a (frames, cells, 2, 8) array.
"""

from __future__ import annotations

import numpy as np

from ..jit import cached_njit

__all__ = ["accumulate_displacement", "gauss_newton_terms"]


@cached_njit(nogil=True)
def _unit_displacement(h, hi, xc, yc, cx, cy, width, height, out):  # pragma: no cover - compiled
    """Fill ``out`` (2, 8) with ``D`` of one frame at canvas point ``(xc, yc)``; False where the frame does not see it.

    ``h`` is the frame-to-canvas homography, ``hi`` its inverse, ``(cx, cy)`` the frame centre.
    """
    den = hi[2, 0] * xc + hi[2, 1] * yc + hi[2, 2]
    x = (hi[0, 0] * xc + hi[0, 1] * yc + hi[0, 2]) / den
    y = (hi[1, 0] * xc + hi[1, 1] * yc + hi[1, 2]) / den
    if x < 0 or x > width - 1 or y < 0 or y > height - 1:
        return False
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    px = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    py = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    a00 = (h[0, 0] - px * h[2, 0]) / w
    a01 = (h[0, 1] - px * h[2, 1]) / w
    a10 = (h[1, 0] - py * h[2, 0]) / w
    a11 = (h[1, 1] - py * h[2, 1]) / w
    u, v = x - cx, y - cy
    # J rows: x' = [u, 0, v, 0, 1, 0, -u u, -u v], y' = [0, u, 0, v, 0, 1, -u v, -v v]
    jx = (u, 0.0, v, 0.0, 1.0, 0.0, -u * u, -u * v)
    jy = (0.0, u, 0.0, v, 0.0, 1.0, -u * v, -v * v)
    for j in range(8):
        out[0, j] = a00 * jx[j] + a01 * jy[j]
        out[1, j] = a10 * jx[j] + a11 * jy[j]
    return True


@cached_njit(nogil=True)
def accumulate_displacement(homographies, inverses, lower, weight, xs, ys, width, height,
                            n_knots):  # pragma: no cover - compiled
    """Sum each frame's displacement per unit parameter into its two knots, per canvas cell.

    Args:
        homographies: (F, 3, 3) float64 frame-to-canvas homographies of the sampled frames.
        inverses: (F, 3, 3) float64 their inverses.
        lower: (F,) int64 the knot before each frame.
        weight: (F,) float64 the weight of that knot (the next one gets ``1 - weight``).
        xs: (N,) float64 canvas x of the cells.
        ys: (N,) float64 canvas y of the cells.
        width: frame width in pixels.
        height: frame height in pixels.
        n_knots: K.

    Returns:
        ``(total, frames)``: (K, N, 2, 8) float64 sums and (N,) float64 frames seeing each cell.
    """
    total = np.zeros((n_knots, len(xs), 2, 8))
    frames = np.zeros(len(xs))
    unit = np.empty((2, 8))
    cx, cy = (width - 1) / 2, (height - 1) / 2
    for f in range(len(homographies)):
        k, w = lower[f], weight[f]
        for n in range(len(xs)):
            if not _unit_displacement(homographies[f], inverses[f], xs[n], ys[n], cx, cy, width, height, unit):
                continue
            frames[n] += 1.0
            for r in range(2):
                for j in range(8):
                    total[k, n, r, j] += w * unit[r, j]
                    total[k + 1, n, r, j] += (1.0 - w) * unit[r, j]
    return total, frames


@cached_njit(nogil=True)
def gauss_newton_terms(homographies, inverses, xs, ys, tensors, observed, field, width, height,
                       keep_weighted):  # pragma: no cover - compiled
    """Each reference frame's information ``sum D' S D``, response ``sum D' S d`` to a field, and ``D' S``.

    Args:
        homographies: (G, 3, 3) float64 reference-frame-to-canvas homographies.
        inverses: (G, 3, 3) float64 their inverses.
        xs: (N,) float64 canvas x of the cells.
        ys: (N,) float64 canvas y of the cells.
        tensors: (N, 2, 2) float64 structure tensor of each cell.
        observed: (N,) bool cells the template observes.
        field: (N, 2) float64 a displacement field of the template (zeros: none).
        width: frame width in pixels.
        height: frame height in pixels.
        keep_weighted: also return ``D' S`` per frame.

    Returns:
        ``(information, response, weighted)``: (G, 8, 8), (G, 8) and (G, 8, N * 2) float64
        (``weighted`` (G, 8, 0) without ``keep_weighted``; zero for cells not seen).
    """
    g, n_cells = len(homographies), len(xs)
    information = np.zeros((g, 8, 8))
    response = np.zeros((g, 8))
    weighted = np.zeros((g, 8, n_cells * 2 if keep_weighted else 0))
    unit = np.empty((2, 8))
    product = np.empty((2, 8))
    cx, cy = (width - 1) / 2, (height - 1) / 2
    for i in range(g):
        for n in range(n_cells):
            if not observed[n]:
                continue
            if not _unit_displacement(homographies[i], inverses[i], xs[n], ys[n], cx, cy, width, height, unit):
                continue
            s = tensors[n]
            for j in range(8):
                product[0, j] = s[0, 0] * unit[0, j] + s[0, 1] * unit[1, j]
                product[1, j] = s[1, 0] * unit[0, j] + s[1, 1] * unit[1, j]
            for a in range(8):
                response[i, a] += product[0, a] * field[n, 0] + product[1, a] * field[n, 1]
                for b in range(8):
                    information[i, a, b] += product[0, a] * unit[0, b] + product[1, a] * unit[1, b]
                if keep_weighted:
                    weighted[i, a, 2 * n] = product[0, a]
                    weighted[i, a, 2 * n + 1] = product[1, a]
    return information, response, weighted
