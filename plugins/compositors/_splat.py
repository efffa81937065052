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

__all__ = ["splat_point", "splat_square", "splat_gaussian", "SIDE_TOLERANCE"]

ROW_MARGIN_PX = 0.01
"""Distance in canvas pixels that a fast-path row keeps from the canvas edges (float32
rounding of its cells is below 1e-4 px on canvases up to 10^4 pixels)."""

SIDE_TOLERANCE = 0.01
"""Relative excess over one canvas pixel below which :func:`splat_square` shrinks a drop
to one canvas pixel. Estimated homographies scale a frame pixel by 1 +- 0.2 % (a
100 000-frame hand-shake capture: 0.998-1.002, three in four above 1), so drops of the
default side (one canvas pixel) would otherwise mostly miss the 2x2 fast path (2.9 ms
against 0.6 ms per 254x496 image); a drop 0.2 % smaller changes none of its weights
by more than 0.002."""


@cached_njit(nogil=True)
def _project(m, x, y):
    """Canvas position of frame pixel ``(x, y)``: inf on the line at infinity (never raises)."""
    den = m[2, 0] * x + m[2, 1] * y + m[2, 2]
    if den == 0.0:
        return math.inf, math.inf
    return (m[0, 0] * x + m[0, 1] * y + m[0, 2]) / den, (m[1, 0] * x + m[1, 1] * y + m[1, 2]) / den


@cached_njit(nogil=True)
def _pixel_size(m):
    """Side of a frame pixel on the canvas, in canvas pixels (the affine part's scale)."""
    return math.sqrt(abs(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])) / abs(m[2, 2])


@cached_njit(nogil=True)
def _row_inside(m, y, w, off, hi_u, hi_v):
    """Whether every pixel centre of frame row ``y`` lands inside the canvas.

    True if ``(u + off, v + off)`` lies in ``[0, hi_u) x [0, hi_v)``, with a margin of
    :data:`ROW_MARGIN_PX` for the float32 arithmetic of :func:`_row_cells`, for the
    canvas position ``(u, v)`` of each centre: a row maps to a segment if the projective
    denominator keeps its sign along it (it is linear in x: both ends positive), and then
    its two ends decide. Not compiled with fastmath: the comparisons guard unchecked writes.
    """
    for x in (0, w - 1):
        den = m[2, 0] * x + m[2, 1] * y + m[2, 2]
        if not den > 0:
            return False
        u, v = _project(m, x, y)
        if not (ROW_MARGIN_PX <= u + off < hi_u - ROW_MARGIN_PX and ROW_MARGIN_PX <= v + off < hi_v - ROW_MARGIN_PX):
            return False
    return True


@cached_njit(nogil=True, fastmath=True, error_model="numpy")
def _row_cells(m, y, off, side, xs, js, is_, axs, ays):
    """Cells and weights of the drops of frame row ``y``, for rows :func:`_row_inside`.

    With ``(u, v)`` a pixel centre's canvas position: ``js, is_`` (int32) are
    ``floor(u + off), floor(v + off)``, and ``axs, ays`` (float32) the fractions
    ``min(side, j + 1 - (u + off)) / side`` of a drop of ``side`` canvas pixels whose
    left (top) edge is at ``u + off`` (``v + off``) that fall in column ``j`` (row ``i``).
    ``m`` is (3, 3) float32 and ``y`` a float32 (an integer row index would promote the
    loop to float64, half as fast); a branch-free loop the compiler vectorises (valid
    where ``u + off, v + off >= 0``: truncation is the floor there). Compiled with
    numpy's error model (a division by zero gives inf instead of raising, which keeps a
    branch out of the loop): the row's ends lie on the canvas, so its denominators,
    linear along the row, have no zero.
    """
    # the matrix in scalars: the loop's stores could alias ``m``, which would stop vectorisation
    a00, a10, a20 = m[0, 0], m[1, 0], m[2, 0]
    bu, bv, bd = m[0, 1] * y + m[0, 2], m[1, 1] * y + m[1, 2], m[2, 1] * y + m[2, 2]
    inv_side = np.float32(1) / side
    for x in range(xs.size):
        inv = np.float32(1) / (a20 * xs[x] + bd)
        u = (a00 * xs[x] + bu) * inv + off
        v = (a10 * xs[x] + bv) * inv + off
        j, i = np.int32(u), np.int32(v)
        js[x], is_[x] = j, i
        axs[x] = min(side, np.float32(j + 1) - u) * inv_side
        ays[x] = min(side, np.float32(i + 1) - v) * inv_side


@cached_njit(nogil=True)
def splat_point(counts, n_frames, homographies, weights, acc):
    """Add each frame pixel to the canvas pixel its centre lands in.

    Args:
        counts: (B, H, W) uint16 or float32 summed frames.
        n_frames: (B,) int64 frames behind each count image.
        homographies: (B, 3, 3) float64 frame-to-canvas homographies.
        weights: (H, W) float32 weight of each frame pixel (0 skips it).
        acc: (Hc, Wc, 2) float32 C-contiguous accumulated counts (``[..., 0]``) and
            frames (``[..., 1]``), updated in place (interleaved: one cache line for
            both; :func:`splat_square` adds through its flat view).
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
                if wt == 0 or not (-0.5 <= u < wc - 0.5 and -0.5 <= v < hc - 0.5):  # NaN too
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
    most 2x2 canvas pixels, with weights ``ax ay``, ``(1 - ax) ay``, ``ax (1 - ay)``,
    ``(1 - ax) (1 - ay)`` (``ax``, ``ay``: the fractions of the drop's width and height
    in its first column and row); they take a fast path: the cells and weights of a
    whole row at once in float32 (:func:`_row_cells`), then the adds without bounds
    checks in rows whose drops all lie on the canvas. Drops larger than one canvas pixel
    by at most :data:`SIDE_TOLERANCE` are made one canvas pixel. Arguments as
    :func:`splat_point`; ``pixfrac`` > 0.
    """
    nb, h, w = counts.shape
    hc, wc = acc.shape[0], acc.shape[1]
    flat = acc.reshape(acc.size)
    xs = np.arange(w).astype(np.float32)
    js, is_ = np.empty(w, np.int32), np.empty(w, np.int32)
    axs, ays = np.empty(w, np.float32), np.empty(w, np.float32)
    for b in range(nb):
        m, m32 = homographies[b], homographies[b].astype(np.float32)
        nf = np.float32(n_frames[b])
        side = pixfrac * _pixel_size(m)
        if side <= 1.0 + SIDE_TOLERANCE:
            side = min(side, 1.0)
        else:
            for y in range(h):
                _square_row(counts[b, y], nf, m, y, weights[y], acc, side)
            continue
        off, side32 = np.float32(0.5 - 0.5 * side), np.float32(side)
        for y in range(h):
            if not _row_inside(m, y, w, off, wc - 1, hc - 1):
                _square_row(counts[b, y], nf, m, y, weights[y], acc, side)
                continue
            _row_cells(m32, np.float32(y), off, side32, xs, js, is_, axs, ays)
            _row_adds(flat, 2 * wc, counts[b, y], weights[y], nf, js, is_, axs, ays)


@cached_njit(nogil=True, fastmath=True)
def _row_adds(flat, stride, counts, weights, nf, js, is_, axs, ays):
    """The 2x2 adds of one frame row's drops, without bounds checks (see :func:`splat_square`).

    ``flat`` is the accumulator raveled (``stride`` = 2 x canvas width floats per canvas
    row); ``counts``, ``weights`` (W,) the row's; the cells and fractions from :func:`_row_cells`.
    """
    for x in range(counts.size):
        k = is_[x] * stride + 2 * js[x]
        ax, ay, wt = axs[x], ays[x], weights[x]
        c, n = np.float32(counts[x]) * wt, nf * wt
        w00 = ax * ay
        w01, w10 = ay - w00, ax - w00
        w11 = np.float32(1) - ax - ay + w00
        flat[k] += c * w00
        flat[k + 1] += n * w00
        flat[k + 2] += c * w01
        flat[k + 3] += n * w01
        k += stride
        flat[k] += c * w10
        flat[k + 1] += n * w10
        flat[k + 2] += c * w11
        flat[k + 3] += n * w11


@cached_njit(nogil=True)
def _square_row(counts, nf, m, y, weights, acc, side):
    """Square drops of side ``side`` canvas pixels of frame row ``y``, with bounds checks.

    For rows at the canvas's edges and drops larger than a canvas pixel; ``counts`` and
    ``weights`` are (W,) that row's.
    """
    hc, wc = acc.shape[0], acc.shape[1]
    half, inv_area = 0.5 * side, 1.0 / (side * side)
    for x in range(counts.size):
        wt = weights[x]
        if wt == 0:
            continue
        u, v = _project(m, x, y)
        if not (abs(u) < 1e9 and abs(v) < 1e9):  # the line at infinity, NaN
            continue
        x0, x1, y0, y1 = u - half, u + half, v - half, v + half
        c, n = counts[x] * wt, nf * wt
        i0, i1 = max(int(math.floor(y0 + 0.5)), 0), min(int(math.floor(y1 + 0.5)), hc - 1)
        j0, j1 = max(int(math.floor(x0 + 0.5)), 0), min(int(math.floor(x1 + 0.5)), wc - 1)
        for i in range(i0, i1 + 1):
            oy = min(y1, i + 0.5) - max(y0, i - 0.5)
            for j in range(j0, j1 + 1):
                _add(acc, i, j, c, n, oy * (min(x1, j + 0.5) - max(x0, j - 0.5)) * inv_area)


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
                if not (abs(u) < 1e9 and abs(v) < 1e9):  # the line at infinity, NaN
                    continue
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
