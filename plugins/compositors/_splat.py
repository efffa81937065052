"""Numba kernels of the ``drizzle`` compositor: forward splats of frame pixel centres.

Conventions: frame and canvas pixel centres at integers, canvas pixel ``(i, j)`` covers
``[j - 0.5, j + 0.5) x [i - 0.5, i + 0.5)``; ``homographies`` map frame pixels to canvas
pixels. Each frame pixel deposits its count ``c`` and its number of frames ``n`` with
the kernel's weights ``w`` (summing to 1 over the canvas) into an interleaved
accumulator: ``acc[..., 0] += w c``, ``acc[..., 1] += w n``. The kernels release the
GIL, so threads fill separate canvases at once.
"""

from __future__ import annotations

import math

import numpy as np
from photonpano.jit import cached_njit

__all__ = ["splat_point", "splat_square", "splat_gaussian"]


@cached_njit(nogil=True, fastmath=True)
def _project(m, x, y):
    den = m[2, 0] * x + m[2, 1] * y + m[2, 2]
    return (m[0, 0] * x + m[0, 1] * y + m[0, 2]) / den, (m[1, 0] * x + m[1, 1] * y + m[1, 2]) / den


@cached_njit(nogil=True)
def _pixel_size(m):
    """Side of a frame pixel on the canvas, in canvas pixels (the affine part's scale)."""
    return math.sqrt(abs(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])) / abs(m[2, 2])


@cached_njit(nogil=True)
def splat_point(counts, n_frames, homographies, weights, acc):
    """Add each frame pixel to the canvas pixel its centre lands in.

    Args:
        counts: (B, H, W) uint16 or float32 summed frames.
        n_frames: (B,) int64 frames behind each count image.
        homographies: (B, 3, 3) float64 frame-to-canvas homographies.
        weights: (H, W) float32 weight of each frame pixel (0 skips it).
        acc: (Hc, Wc, 2) float32 accumulated counts (``[..., 0]``) and frames
            (``[..., 1]``), updated in place (interleaved: one cache line for both).
    """
    nb, h, w = counts.shape
    hc, wc = acc.shape[0], acc.shape[1]
    for b in range(nb):
        m = homographies[b]
        nf = np.float32(n_frames[b])
        for y in range(h):
            for x in range(w):
                wt = weights[y, x]
                u, v = _project(m, x, y)
                if wt == 0 or u < -0.5 or v < -0.5:
                    continue
                j, i = int(u + 0.5), int(v + 0.5)
                if i < hc and j < wc:
                    acc[i, j, 0] += counts[b, y, x] * wt
                    acc[i, j, 1] += nf * wt


@cached_njit(nogil=True)
def _add(acc, i, j, c, n, weight):
    """Add one weighted drop to canvas pixel ``(i, j)`` if it lies on the canvas."""
    if 0 <= i < acc.shape[0] and 0 <= j < acc.shape[1] and weight > 0:
        acc[i, j, 0] += np.float32(c * weight)
        acc[i, j, 1] += np.float32(n * weight)


@cached_njit(nogil=True, fastmath=True)
def splat_square(counts, n_frames, homographies, weights, acc, pixfrac):
    """Spread each frame pixel over the canvas pixels a square drop overlaps, by area.

    The drop is an axis-aligned square of side ``pixfrac`` frame pixels centred on the
    frame pixel's centre (a rotation of the frame is ignored for the drop's shape).
    Drops of at most one canvas pixel (``pixfrac * scale <= 1``, the default) touch at
    most 2x2 canvas pixels and take a fast path. Arguments as :func:`splat_point`;
    ``pixfrac`` > 0.
    """
    nb, h, w = counts.shape
    hc, wc = acc.shape[0], acc.shape[1]
    for b in range(nb):
        m = homographies[b]
        nf = np.float32(n_frames[b])
        side = pixfrac * _pixel_size(m)
        half = 0.5 * side
        inv_area = 1.0 / (side * side)
        small = side <= 1.0
        for y in range(h):
            for x in range(w):
                wt = weights[y, x]
                if wt == 0:
                    continue
                u, v = _project(m, x, y)
                x0, x1, y0, y1 = u - half, u + half, v - half, v + half
                c = counts[b, y, x] * wt
                n = nf * wt
                if small:  # overlaps with (i0, j0) and the next pixel along each axis
                    j0, i0 = int(math.floor(x0 + 0.5)), int(math.floor(y0 + 0.5))
                    ox = min(x1, j0 + 0.5) - x0
                    oy = min(y1, i0 + 0.5) - y0
                    ox1, oy1 = side - ox, side - oy
                    if 0 <= i0 and i0 + 1 < hc and 0 <= j0 and j0 + 1 < wc:  # inside: no checks
                        w00, w01 = np.float32(ox * oy * inv_area), np.float32(ox1 * oy * inv_area)
                        w10, w11 = np.float32(ox * oy1 * inv_area), np.float32(ox1 * oy1 * inv_area)
                        cf, nn = np.float32(c), np.float32(n)
                        acc[i0, j0, 0] += cf * w00
                        acc[i0, j0 + 1, 0] += cf * w01
                        acc[i0 + 1, j0, 0] += cf * w10
                        acc[i0 + 1, j0 + 1, 0] += cf * w11
                        acc[i0, j0, 1] += nn * w00
                        acc[i0, j0 + 1, 1] += nn * w01
                        acc[i0 + 1, j0, 1] += nn * w10
                        acc[i0 + 1, j0 + 1, 1] += nn * w11
                        continue
                    _add(acc, i0, j0, c, n, ox * oy * inv_area)
                    _add(acc, i0, j0 + 1, c, n, ox1 * oy * inv_area)
                    _add(acc, i0 + 1, j0, c, n, ox * oy1 * inv_area)
                    _add(acc, i0 + 1, j0 + 1, c, n, ox1 * oy1 * inv_area)
                    continue
                i0, i1 = max(int(math.floor(y0 + 0.5)), 0), min(int(math.floor(y1 + 0.5)), hc - 1)
                j0, j1 = max(int(math.floor(x0 + 0.5)), 0), min(int(math.floor(x1 + 0.5)), wc - 1)
                for i in range(i0, i1 + 1):
                    oy = min(y1, i + 0.5) - max(y0, i - 0.5)
                    for j in range(j0, j1 + 1):
                        weight = oy * (min(x1, j + 0.5) - max(x0, j - 0.5)) * inv_area
                        if weight > 0:
                            acc[i, j, 0] += np.float32(c * weight)
                            acc[i, j, 1] += np.float32(n * weight)


@cached_njit(nogil=True)
def splat_gaussian(counts, n_frames, homographies, weights, acc, pixfrac):
    """Spread each frame pixel with a Gaussian of FWHM ``pixfrac`` frame pixels.

    Weights are the (separable) Gaussian at the canvas pixel centres within 3 sigma (at
    least the 3x3 neighbourhood), normalised to sum to 1. Arguments as
    :func:`splat_square`.
    """
    nb, h, w = counts.shape
    hc, wc = acc.shape[0], acc.shape[1]
    for b in range(nb):
        m = homographies[b]
        nf = np.float32(n_frames[b])
        sigma = pixfrac * _pixel_size(m) / 2.3548
        radius = max(1, int(math.ceil(3 * sigma)))
        inv = 1.0 / (2 * sigma * sigma)
        wx = np.empty(2 * radius + 1)
        wy = np.empty(2 * radius + 1)
        for y in range(h):
            for x in range(w):
                wt = weights[y, x]
                if wt == 0:
                    continue
                u, v = _project(m, x, y)
                ci, cj = int(math.floor(v + 0.5)), int(math.floor(u + 0.5))
                sx = sy = 0.0
                for k in range(2 * radius + 1):
                    wx[k] = math.exp(-(cj - radius + k - u) ** 2 * inv)
                    wy[k] = math.exp(-(ci - radius + k - v) ** 2 * inv)
                    sx += wx[k]
                    sy += wy[k]
                norm = wt / (sx * sy)
                c = counts[b, y, x] * norm
                n = nf * norm
                for i in range(max(ci - radius, 0), min(ci + radius, hc - 1) + 1):
                    a = wy[i - ci + radius]
                    for j in range(max(cj - radius, 0), min(cj + radius, wc - 1) + 1):
                        weight = a * wx[j - cj + radius]
                        acc[i, j, 0] += np.float32(c * weight)
                        acc[i, j, 1] += np.float32(n * weight)
