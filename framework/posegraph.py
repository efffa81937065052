"""The pose graph of a pairwise level: chaining and the joint robust solve (pure numerics).

Consecutive registrations are chained into keyframe homographies
(:func:`chain_keyframes`); with longer-offset pairs the keyframes are solved jointly
(:func:`refine_keyframes`), a robust Levenberg-Marquardt over the eight homography
parameters (:func:`robust_least_squares`) with normal equations assembled pair by pair
(:class:`PairJacobian`) and a banded solve (:class:`NormalMatrix`).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .errors import StageError
from .records import PairRegistrations

__all__ = ["chain_keyframes", "refine_keyframes", "robust_least_squares", "PairJacobian", "NormalMatrix",
           "pairs_at_offsets", "corner_disagreement", "median_disagreement", "pair_weights"]

MAX_BAND_BYTES = 2 ** 28
"""Largest band storage of a :class:`NormalMatrix` (256 MiB); wider bands (loop closures) stay sparse."""


def chain_keyframes(current: NDArray[np.float64], pairs: PairRegistrations) -> NDArray[np.float64]:
    """Chain consecutive pair registrations into homographies of the keyframes.

    Pair g maps merged frame g+1 to merged frame g. Its *residual* with respect to the
    current estimate, ``inv(current[g]^-1 current[g+1]) @ M_g``, is what the locator
    adds; a failed pair's residual is bridged by linear interpolation of its
    neighbours' residual parameters (p1..p8). The first keyframe keeps its current
    homography, which fixes the panorama's coordinate frame.

    Args:
        current: (G, 3, 3) float64 current frame-to-panorama homographies of the
            reference frames.
        pairs: G - 1 registrations of consecutive merged frames.

    Returns:
        (G, 3, 3) float64 new frame-to-panorama homographies of the reference frames.

    Raises:
        StageError: if every pair failed to register.
    """
    predicted = np.linalg.inv(current[:-1]) @ current[1:]
    residual = geometry.params_from_homographies(np.linalg.inv(predicted) @ pairs.homographies)
    ok = pairs.ok
    if len(ok) and not ok.any():
        raise StageError("locator", "?", f"all {len(ok)} pairs of merged frames failed to register")
    if not ok.all():
        idx = np.arange(len(ok))
        for k in range(8):
            residual[~ok, k] = np.interp(idx[~ok], idx[ok], residual[ok, k])
    steps = predicted @ geometry.homographies_from_params(residual)
    out = np.empty_like(current)
    out[0] = current[0]
    for g, step in enumerate(steps):
        out[g + 1] = out[g] @ step
    return geometry.normalize(out)


def refine_keyframes(initial: NDArray[np.float64], pair_index: NDArray[np.int64],
                     pairs: PairRegistrations, width: int, height: int) -> NDArray[np.float64]:
    """Adjust keyframe homographies to agree with every registered pair at once.

    A pose-graph least-squares problem (as in bundle adjustment for stitching, Brown and
    Lowe 2007, here on homographies): for each successful pair ``(a, b)`` with
    homography ``M`` (b to a), a 3x3 grid of points ``x`` of frame b should land on the
    same panorama point through both keyframes, ``K_a M x == K_b x``. Residuals are
    measured in frame a's pixels, ``M x - inv(K_a) K_b x``, weighted by the square root
    of the pair's inlier count, with a soft-L1 loss against outliers, and minimised by
    :func:`robust_least_squares`. The first keyframe is held fixed (gauge). With only
    consecutive pairs this reproduces the chain; pairs further apart in time remove the
    random-walk drift of chaining.

    Args:
        initial: (G, 3, 3) float64 starting keyframe homographies (e.g. the chain).
        pair_index: (P, 2) int64 keyframe indices ``(a, b)`` of each pair.
        pairs: the P pair registrations; failed pairs are ignored.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (G, 3, 3) float64 refined keyframe homographies.
    """
    g = len(initial)
    use = pairs.ok & (pair_index[:, 0] != pair_index[:, 1])
    if g < 2 or not use.any():
        return initial
    a, b = pair_index[use, 0], pair_index[use, 1]
    gx, gy = np.meshgrid(np.linspace(0, width - 1, 3), np.linspace(0, height - 1, 3))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (9, 2) points of frame b
    mapped = geometry.apply(pairs.homographies[use], grid)  # (E, 9, 2) points of frame a
    weight = pair_weights(pairs.inliers[use])
    # Each keyframe is solved as a small update of its starting value, K_g = initial_g @ H(d_g):
    # the 8 parameters of d_g are all of order 1e-3 and well conditioned, whereas the
    # absolute parameters of keyframes far along a pan (hundreds of pixels) are not.
    # Residuals and Jacobians are compiled (one pass over the pairs, on one core while the
    # workers wait): _posegraph_compiled.pair_residuals.
    from ._posegraph_compiled import pair_residuals

    relative0 = np.linalg.inv(initial[a]) @ initial[b]  # (E, 3, 3) starting b-to-a maps

    def updates(free: NDArray[np.float64]) -> NDArray[np.float64]:
        """(G, 3, 3) keyframe updates H(d_g), the gauge keyframe's the identity."""
        return geometry.homographies_from_params(np.concatenate([np.zeros((1, 8)), free.reshape(g - 1, 8)]))

    def linearise(free: NDArray[np.float64]) -> tuple[NDArray[np.float64], PairJacobian]:
        """Weighted residuals in frame a's pixels, ``M x - inv(K_a) K_b x``, and their Jacobian.

        Measured in the frame's own pixels (as Brown and Lowe do), not on the panorama:
        there, shrinking every keyframe would shrink every residual, a degenerate
        direction the solver follows on long captures.
        """
        residual, ja, jb = pair_residuals(free, relative0, mapped, grid, weight, a, b)
        return residual, PairJacobian(ja, jb, a - 1, b - 1, g - 1)

    return initial @ updates(robust_least_squares(linearise, np.zeros((g - 1) * 8)))


class PairJacobian:
    """The Jacobian of a pose graph's residuals: each pair's residuals depend on two blocks of unknowns.

    Pair e's R residuals depend on the D unknowns of block ``first_block[e]`` (columns
    ``D * block .. D * block + D - 1``) through ``first[e]`` and on those of
    ``second_block[e]`` through ``second[e]``; block -1 is held fixed (it has no
    columns). Its normal equations are assembled block by block, without a sparse
    matrix product (:meth:`normal_equations`).

    Args:
        first: (E, R, D) float64 derivatives by the first block's unknowns.
        second: (E, R, D) float64 derivatives by the second block's unknowns.
        first_block: (E,) int64 block of each pair's first derivatives (-1: fixed).
        second_block: (E,) int64 block of each pair's second derivatives (-1: fixed).
        n_blocks: number of blocks; the unknowns are ``n_blocks * D``.
    """

    def __init__(self, first: NDArray[np.float64], second: NDArray[np.float64], first_block: NDArray[np.int64],
                 second_block: NDArray[np.int64], n_blocks: int) -> None:
        self.first, self.second = first, second
        self.first_block, self.second_block = np.asarray(first_block), np.asarray(second_block)
        self.n_blocks = int(n_blocks)

    def normal_equations(self, weights: NDArray[np.float64], residual: NDArray[np.float64]
                         ) -> tuple[NormalMatrix, NDArray[np.float64]]:
        """``J^T W J`` and ``J^T W r`` for residual weights ``W = diag(weights)``.

        Args:
            weights: (E * R,) float64 weight of each residual (pair-major, as ``residual``).
            residual: (E * R,) float64 residuals.

        Returns:
            ``(normal, gradient)``: the (N, N) :class:`NormalMatrix` and the (N,) float64
            gradient, N = ``n_blocks * D``.
        """
        e, r, d = self.first.shape
        n = self.n_blocks * d
        both = (self.first_block >= 0) & (self.second_block >= 0)
        band = d * int(np.abs(self.first_block[both] - self.second_block[both]).max(initial=0)) + d - 1
        if (band + 1) * n * 8 <= MAX_BAND_BYTES:  # compiled, straight into the band (one pass over the pairs)
            from ._posegraph_compiled import banded_normal_equations

            ab, gradient = banded_normal_equations(
                np.ascontiguousarray(self.first, np.float64), np.ascontiguousarray(self.second, np.float64),
                self.first_block.astype(np.int64), self.second_block.astype(np.int64),
                np.ascontiguousarray(weights, np.float64), np.ascontiguousarray(residual, np.float64),
                self.n_blocks, band)
            return NormalMatrix.from_band(ab), gradient
        w = weights.reshape(e, r)
        wr = w * residual.reshape(e, r)
        columns = np.arange(d)
        sides = ((self.first, self.first_block), (self.second, self.second_block))
        gradient = np.zeros(n)
        for jac, block in sides:
            keep = block >= 0
            index = (d * block[keep])[:, None] + columns
            gradient += np.bincount(index.ravel(), np.einsum("erd,er->ed", jac[keep], wr[keep]).ravel(), minlength=n)
        rows, cols, values = [], [], []
        for left, row_block in sides:
            weighted = left * w[..., None]
            for right, col_block in sides:
                keep = (row_block >= 0) & (col_block >= 0) & (row_block <= col_block)
                product = weighted[keep].swapaxes(1, 2) @ right[keep]  # (K, D, D)
                rows.append(np.broadcast_to((d * row_block[keep])[:, None, None] + columns[:, None], product.shape))
                cols.append(np.broadcast_to((d * col_block[keep])[:, None, None] + columns, product.shape))
                values.append(product)
        row_index, col_index, entries = (np.concatenate([x.reshape(-1) for x in part]) for part in (rows, cols, values))
        return NormalMatrix(row_index, col_index, entries, n), gradient


class NormalMatrix:
    """A symmetric positive definite (N, N) matrix given by entries on and above its diagonal.

    Entries may repeat (they are summed). Pose graphs order their unknowns in time and
    pair frames a bounded offset apart, so the matrix is banded: it is stored in LAPACK's
    upper band form and solved by banded Cholesky (``solveh_banded``, ``N u^2`` for
    bandwidth u), several times faster than a general sparse LU; wider bands (loop
    closures) fall back to SuperLU.

    Args:
        rows: (K,) int64 row of each entry.
        cols: (K,) int64 column of each entry (entries below the diagonal are ignored).
        values: (K,) float64 values.
        n: matrix size N.
        max_band_bytes: largest band storage; wider bands are kept sparse.

    Attributes:
        diagonal: (N,) float64 diagonal.
    """

    def __init__(self, rows: NDArray[np.int64], cols: NDArray[np.int64], values: NDArray[np.float64], n: int,
                 max_band_bytes: float = MAX_BAND_BYTES) -> None:
        upper = cols >= rows
        rows, cols, values, self.n = rows[upper], cols[upper], values[upper], int(n)
        on = rows == cols
        self.diagonal = np.bincount(rows[on], values[on], minlength=self.n)
        self.band = int((cols - rows).max(initial=0))
        self._ab: NDArray[np.float64] | None = None
        self._entries: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]] | None = None
        if (self.band + 1) * self.n * 8 <= max_band_bytes:
            index = (self.band + rows - cols) * self.n + cols
            sums = np.asarray(np.bincount(index, values, minlength=(self.band + 1) * self.n), np.float64)  # no copy
            self._ab = sums.reshape(-1, self.n)
        else:
            self._entries = rows, cols, values

    @classmethod
    def from_band(cls, ab: NDArray[np.float64]) -> NormalMatrix:
        """The matrix of a (u + 1, N) float64 upper band ``ab[u + i - j, j] = A[i, j]`` (kept, not copied)."""
        matrix = cls.__new__(cls)
        matrix.band, matrix.n = ab.shape[0] - 1, ab.shape[1]
        matrix._ab, matrix._entries = ab, None
        matrix.diagonal = ab[matrix.band].copy()
        return matrix

    def entries(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """``(rows, cols, values)``: (K,) int64, int64 and float64 entries on and above the diagonal."""
        if self._entries is not None:
            return self._entries
        assert self._ab is not None  # one of the two storages is always set
        k, cols = np.nonzero(self._ab)
        return cols - (self.band - k), cols, self._ab[k, cols]

    def solve(self, damping: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        """Solve ``(A + diag(damping)) x = rhs`` for (N,) float64 ``x``."""
        from scipy.linalg import LinAlgError, solveh_banded

        if self._ab is not None:
            ab = self._ab.copy()
            ab[self.band] += damping
            try:
                return solveh_banded(ab, rhs, overwrite_ab=True, check_finite=False)
            except LinAlgError:
                pass
        from scipy.sparse import coo_matrix, diags
        from scipy.sparse.linalg import spsolve

        rows, cols, values = self.entries()
        off = rows != cols
        full = coo_matrix((np.concatenate([values, values[off]]),
                           (np.concatenate([rows, cols[off]]), np.concatenate([cols, rows[off]]))),
                          shape=(self.n, self.n))
        return spsolve((full + diags(damping)).tocsc(), rhs)


def robust_least_squares(linearise: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], Any]],
                         x0: NDArray[np.float64], *, f_scale: float = 1.0, max_iterations: int = 50,
                         tolerance: float = 1e-6) -> NDArray[np.float64]:
    """Minimise ``sum(rho(r_i(x)^2))`` with the soft-L1 loss by Levenberg-Marquardt on a sparse Jacobian.

    ``rho(z) = 2 (sqrt(1 + z / f^2) - 1) f^2`` (scipy's ``soft_l1``), handled by
    iteratively reweighted least squares: each step solves the damped, reweighted normal
    equations ``(J^T W J + lambda diag(J^T W J)) dx = -J^T W r`` with
    ``W = diag(1 / sqrt(1 + r^2 / f^2))`` by a direct factorisation
    (:class:`NormalMatrix`: banded Cholesky, else SuperLU). For pose graphs, whose
    normal matrix is banded, this is 3-4x faster than scipy's ``least_squares`` with
    ``lsmr`` (which it replaced) and linear in the number of keyframes. Reference:
    Triggs et al., "Bundle Adjustment - A Modern Synthesis", 2000, Secs. 4.3 and 6.

    Args:
        linearise: ``linearise(x)`` returns the residuals ((R,) float64) and their
            Jacobian at ``x``: an (R, N) scipy sparse matrix, or a :class:`PairJacobian`.
        x0: (N,) float64 start.
        f_scale: residual scale of the loss (residuals' units); beyond it residuals are
            progressively down-weighted.
        max_iterations: accepted steps at most.
        tolerance: stop when a step changes the cost or every parameter relatively by less.

    Returns:
        (N,) float64 solution.
    """
    def loss(res: NDArray[np.float64]) -> float:
        return float(np.sum(2 * f_scale ** 2 * (np.sqrt(1 + (res / f_scale) ** 2) - 1)))

    def normal_equations(jacobian: Any, w: NDArray[np.float64],
                         res: NDArray[np.float64]) -> tuple[NormalMatrix, NDArray[np.float64]]:
        """``J^T W J`` and ``J^T W r`` for either kind of Jacobian."""
        if isinstance(jacobian, PairJacobian):
            return jacobian.normal_equations(w, res)
        weighted = jacobian.T.multiply(w).tocsr()
        normal = (weighted @ jacobian).tocoo()
        return NormalMatrix(normal.row, normal.col, normal.data, weighted.shape[0]), weighted @ res

    x = np.asarray(x0, np.float64)
    residual, jacobian = linearise(x)
    cost, damping = loss(residual), 1e-3
    for _ in range(max_iterations):
        normal, gradient = normal_equations(jacobian, 1 / np.sqrt(1 + (residual / f_scale) ** 2), residual)
        scale = np.maximum(normal.diagonal, 1e-12)
        while True:
            step = -normal.solve(damping * scale, gradient)
            trial = x + step
            trial_residual, trial_jacobian = linearise(trial)
            trial_cost = loss(trial_residual)
            if np.isfinite(trial_cost) and trial_cost <= cost:
                break
            damping *= 10
            if damping > 1e8:
                return x
        converged = (cost - trial_cost <= tolerance * cost
                     or np.all(np.abs(step) <= tolerance * (np.abs(x) + tolerance)))
        x, residual, jacobian, cost = trial, trial_residual, trial_jacobian, trial_cost
        damping = max(damping / 10, 1e-9)
        if converged:
            break
    return x


def pair_weights(inliers: NDArray[np.int64]) -> NDArray[np.float64]:
    """Each pair's weight in a pose graph: the square root of its inliers over their median (each at least 1).

    Args:
        inliers: (E,) int64 inlier counts of the registered pairs (E >= 1).

    Returns:
        (E,) float64 weights of the pairs' residuals.
    """
    return np.sqrt(np.maximum(inliers, 1) / max(float(np.median(inliers)), 1.0))


def pairs_at_offsets(count: int, offsets: tuple[int, ...]) -> NDArray[np.int64]:
    """Return (P, 2) int64 pairs ``(g, g + k)`` of ``count`` merged frames for each offset k.

    Offset 1 (consecutive pairs) is always included, so the pairs chain all frames.
    """
    ks = sorted({1, *offsets})
    rows = [np.stack([np.arange(count - k), np.arange(k, count)], axis=1) for k in ks if k < count]
    return np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 2), np.int64)


def corner_disagreement(a: NDArray[np.float64], b: NDArray[np.float64], width: int,
                         height: int) -> NDArray[np.float64]:
    """Largest corner distance in pixels between (P, 3, 3) homographies ``a`` and ``b``."""
    c = geometry.corners(width, height)
    return np.linalg.norm(geometry.apply(a, c) - geometry.apply(b, c), axis=-1).max(axis=-1)


def median_disagreement(keyframes: NDArray[np.float64], pair_index: NDArray[np.int64], pairs: PairRegistrations,
                        use: NDArray[np.bool_], width: int, height: int) -> float:
    """Median :func:`corner_disagreement` (pixels) of the ``use`` pairs' homographies with the keyframes' maps.

    Args:
        keyframes: (G, 3, 3) float64 keyframe homographies.
        pair_index: (P, 2) int64 keyframe indices ``(a, b)`` of each pair.
        pairs: the P registrations (homography b to a).
        use: (P,) bool the pairs to compare (at least one).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        The median, in pixels of frame a (NaN where the keyframes are not finite).
    """
    relative = np.linalg.inv(keyframes[pair_index[use, 0]]) @ keyframes[pair_index[use, 1]]
    return float(np.median(corner_disagreement(pairs.homographies[use], relative, width, height)))
