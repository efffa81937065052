"""Compiled kernels of the pose graph (numba), imported by :mod:`photonpano.posegraph` on first use.

The joint solve at the end of level 1 runs on one core while the executor's workers
wait, so its per-pair arithmetic is compiled: the residuals and Jacobians of
:func:`~photonpano.posegraph.refine_keyframes` (:func:`pair_residuals`) and the
banded normal equations of :class:`~photonpano.posegraph.PairJacobian`
(:func:`banded_normal_equations`), each one pass over the pairs instead of some
twenty numpy passes over (E, 9, 2, 8) arrays.
"""

from __future__ import annotations

import numpy as np

from .jit import cached_njit

__all__ = ["pair_residuals", "banded_normal_equations"]


@cached_njit(nogil=True)
def pair_residuals(free, relative0, mapped, grid, weight, first, second):  # pragma: no cover - compiled
    """Weighted residuals and Jacobians of a pose graph's pairs (see ``refine_keyframes``).

    Keyframe g's update is ``H(d_g)`` with ``d_g = free[8 (g - 1): 8 g]`` (paper Eq. 4
    parametrisation ``[[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]``), the identity for
    g = 0. For pair e = (a, b) and grid point x of frame b: ``y = H(d_b) x``,
    ``z = R0_e y``, ``w = inv(H(d_a)) z``; the residual is ``mapped[e] - w`` (frame a's
    pixels) and its derivatives follow from ``H(d_a) w = z``.

    Args:
        free: ((G - 1) * 8,) float64 parameters of the keyframes' updates.
        relative0: (E, 3, 3) float64 starting b-to-a maps ``inv(K_a) K_b``.
        mapped: (E, Q, 2) float64 grid points mapped by the pairs' measured homographies.
        grid: (Q, 2) float64 grid points of frame b, pixels.
        weight: (E,) float64 weight of each pair's residuals.
        first: (E,) int64 keyframe a of each pair.
        second: (E,) int64 keyframe b of each pair.

    Returns:
        ``(residual, ja, jb)``: (E * Q * 2,) float64 weighted residuals (pair, point,
        coordinate major to minor) and (E, Q * 2, 8) float64 weighted derivatives by the
        parameters of keyframes a and b.
    """
    e_count, q_count = mapped.shape[0], grid.shape[0]
    residual = np.empty(e_count * q_count * 2)
    ja = np.zeros((e_count, q_count * 2, 8))
    jb = np.zeros((e_count, q_count * 2, 8))
    ua = np.empty((3, 3))
    ub = np.empty((3, 3))
    for e in range(e_count):
        for which in range(2):
            g = first[e] if which == 0 else second[e]
            u = ua if which == 0 else ub
            if g == 0:
                for i in range(3):
                    for j in range(3):
                        u[i, j] = 1.0 if i == j else 0.0
            else:
                p = free[8 * (g - 1): 8 * g]
                u[0, 0], u[0, 1], u[0, 2] = 1.0 + p[0], p[2], p[4]
                u[1, 0], u[1, 1], u[1, 2] = p[1], 1.0 + p[3], p[5]
                u[2, 0], u[2, 1], u[2, 2] = p[6], p[7], 1.0
        # inverse of H(d_a) by its adjugate
        c00 = ua[1, 1] * ua[2, 2] - ua[1, 2] * ua[2, 1]
        c01 = ua[0, 2] * ua[2, 1] - ua[0, 1] * ua[2, 2]
        c02 = ua[0, 1] * ua[1, 2] - ua[0, 2] * ua[1, 1]
        c10 = ua[1, 2] * ua[2, 0] - ua[1, 0] * ua[2, 2]
        c11 = ua[0, 0] * ua[2, 2] - ua[0, 2] * ua[2, 0]
        c12 = ua[0, 2] * ua[1, 0] - ua[0, 0] * ua[1, 2]
        c20 = ua[1, 0] * ua[2, 1] - ua[1, 1] * ua[2, 0]
        c21 = ua[0, 1] * ua[2, 0] - ua[0, 0] * ua[2, 1]
        c22 = ua[0, 0] * ua[1, 1] - ua[0, 1] * ua[1, 0]
        r = relative0[e]
        s = weight[e]
        for q in range(q_count):
            x, y = grid[q, 0], grid[q, 1]
            # frame b after its update, and d(y)/d(params of b)
            db = ub[2, 0] * x + ub[2, 1] * y + ub[2, 2]
            yu = (ub[0, 0] * x + ub[0, 1] * y + ub[0, 2]) / db
            yv = (ub[1, 0] * x + ub[1, 1] * y + ub[1, 2]) / db
            dyu = (x / db, 0.0, y / db, 0.0, 1.0 / db, 0.0, -yu * x / db, -yu * y / db)
            dyv = (0.0, x / db, 0.0, y / db, 0.0, 1.0 / db, -yv * x / db, -yv * y / db)
            # into frame a's starting pixels, and d(z)/d(y)
            dr = r[2, 0] * yu + r[2, 1] * yv + r[2, 2]
            zu = (r[0, 0] * yu + r[0, 1] * yv + r[0, 2]) / dr
            zv = (r[1, 0] * yu + r[1, 1] * yv + r[1, 2]) / dr
            dz00, dz01 = (r[0, 0] - zu * r[2, 0]) / dr, (r[0, 1] - zu * r[2, 1]) / dr
            dz10, dz11 = (r[1, 0] - zv * r[2, 0]) / dr, (r[1, 1] - zv * r[2, 1]) / dr
            # undo frame a's update: w = inv(H_a) z
            dw = c20 * zu + c21 * zv + c22
            wu = (c00 * zu + c01 * zv + c02) / dw
            wv = (c10 * zu + c11 * zv + c12) / dw
            # H_a w = z: d(proj(H_a w))/d(params of a) and d(proj(H_a w))/dw
            da = ua[2, 0] * wu + ua[2, 1] * wv + ua[2, 2]
            hu = (ua[0, 0] * wu + ua[0, 1] * wv + ua[0, 2]) / da
            hv = (ua[1, 0] * wu + ua[1, 1] * wv + ua[1, 2]) / da
            dhu = (wu / da, 0.0, wv / da, 0.0, 1.0 / da, 0.0, -hu * wu / da, -hu * wv / da)
            dhv = (0.0, wu / da, 0.0, wv / da, 0.0, 1.0 / da, -hv * wu / da, -hv * wv / da)
            j00, j01 = (ua[0, 0] - hu * ua[2, 0]) / da, (ua[0, 1] - hu * ua[2, 1]) / da
            j10, j11 = (ua[1, 0] - hv * ua[2, 0]) / da, (ua[1, 1] - hv * ua[2, 1]) / da
            det = j00 * j11 - j01 * j10
            i00, i01, i10, i11 = j11 / det, -j01 / det, -j10 / det, j00 / det
            # dw/dz = inv(jw); dw/dparams_a = -inv(jw) dh, so d residual/d params_a = inv(jw) dh
            m00 = i00 * dz00 + i01 * dz10
            m01 = i00 * dz01 + i01 * dz11
            m10 = i10 * dz00 + i11 * dz10
            m11 = i10 * dz01 + i11 * dz11
            row = 2 * q
            residual[e * q_count * 2 + row] = s * (mapped[e, q, 0] - wu)
            residual[e * q_count * 2 + row + 1] = s * (mapped[e, q, 1] - wv)
            for k in range(8):
                ja[e, row, k] = s * (i00 * dhu[k] + i01 * dhv[k])
                ja[e, row + 1, k] = s * (i10 * dhu[k] + i11 * dhv[k])
                jb[e, row, k] = -s * (m00 * dyu[k] + m01 * dyv[k])
                jb[e, row + 1, k] = -s * (m10 * dyu[k] + m11 * dyv[k])
    return residual, ja, jb


@cached_njit(nogil=True)
def banded_normal_equations(first, second, first_block, second_block, weights, residual, n_blocks,
                            band):  # pragma: no cover - compiled
    """``J^T W J`` in LAPACK's upper band form and ``J^T W r`` of a :class:`PairJacobian`.

    Args:
        first: (E, R, D) float64 derivatives by the first block's unknowns.
        second: (E, R, D) float64 derivatives by the second block's unknowns.
        first_block: (E,) int64 first block of each pair (-1: fixed, no unknowns).
        second_block: (E,) int64 second block of each pair (-1: fixed).
        weights: (E * R,) float64 residual weights.
        residual: (E * R,) float64 residuals.
        n_blocks: number of blocks (N = n_blocks * D unknowns).
        band: upper bandwidth u, at least ``D * max|second_block - first_block| + D - 1``.

    Returns:
        ``(ab, gradient)``: (u + 1, N) float64 with ``ab[u + i - j, j] = A[i, j]`` for
        ``i <= j`` (``scipy.linalg.solveh_banded``'s layout) and (N,) float64. Both sides
        of a pair on one block add all four products, each on the upper triangle (as
        the entries of the numpy path).
    """
    e_count, r_count, d = first.shape
    n = n_blocks * d
    ab = np.zeros((band + 1, n))
    gradient = np.zeros(n)
    wj = np.empty((2, r_count, d))
    for e in range(e_count):
        blocks = (first_block[e], second_block[e])
        for side in range(2):
            jac = first if side == 0 else second
            for r in range(r_count):
                w = weights[e * r_count + r]
                for k in range(d):
                    wj[side, r, k] = w * jac[e, r, k]
            block = blocks[side]
            if block >= 0:
                for k in range(d):
                    total = 0.0
                    for r in range(r_count):
                        total += wj[side, r, k] * residual[e * r_count + r]
                    gradient[d * block + k] += total
        for left in range(2):
            row_block = blocks[left]
            if row_block < 0:
                continue
            for right in range(2):
                col_block = blocks[right]
                if col_block < row_block:
                    continue
                jac = first if right == 0 else second
                for i in range(d):
                    row = d * row_block + i
                    for j in range(d):
                        col = d * col_block + j
                        if col < row:
                            continue
                        total = 0.0
                        for r in range(r_count):
                            total += wj[left, r, i] * jac[e, r, j]
                        ab[band + row - col, col] += total
    return ab, gradient
