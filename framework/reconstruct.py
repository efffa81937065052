"""The stratified re-sampling loop and the final panorama, on built stage objects.

``estimate_motion`` iterates the paper's four steps (Sec. 4) over levels; each level's
locate step is chained into keyframe homographies and turned into a smooth correction of
the per-frame trajectory. ``assemble_panorama`` warps every binary frame onto one canvas.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .compose import Panorama, assemble_panorama, canvas_homographies, panorama_views  # noqa: F401 (moved there)
from .errors import StageError
from .executor import Executor, SerialExecutor
from .stages import Groups, Interpolator, Locator, MergedFrames, Merger, PairRegistrations, PhotonSource, Resampler

__all__ = ["LevelResult", "chain_keyframes", "refine_keyframes", "pairs_at_offsets", "plausible",
           "locate_keyframes", "estimate_motion", "Panorama", "canvas_homographies", "assemble_panorama"]


@dataclass
class LevelResult:
    """What one level produced.

    Attributes:
        level: 1-based level number.
        groups: the level's virtual exposures.
        merged: the merged frames (dropped after the level unless kept for dumps).
        pairs: the level's pair registrations.
        pair_index: (P, 2) int64 merged-frame indices ``(a, b)`` of each pair; ``a`` is
            -1 where frame b was registered against the panorama of the current estimate.
        keyframes: (G, 3, 3) float64 chained homographies at the reference frames.
        homographies: (T, 3, 3) float64 per-frame homographies after the level.
        timings_s: wall time of each stage in seconds.
        rejected_keyframes: keyframes whose solved update was implausible and was
            bridged from their neighbours instead.
        template: the panorama the next level registers against, when already built
            (what a checkpoint keeps for ``estimate_motion(template=...)``), else None.
    """

    level: int
    groups: Groups
    merged: MergedFrames | None
    pairs: PairRegistrations
    pair_index: NDArray[np.int64]
    keyframes: NDArray[np.float64]
    homographies: NDArray[np.float64]
    timings_s: dict[str, float] = field(default_factory=dict)
    rejected_keyframes: int = 0
    locator_cache: dict[str, int] | None = None
    template: Panorama | None = None

    def statistics(self) -> dict[str, Any]:
        """Return JSON-ready per-level statistics.

        ``failed_pairs`` counts primary registrations (consecutive pairs, or merged
        frames against the panorama) that failed and were bridged; ``extra_pairs_used``
        counts longer-offset pairs that passed the checks; matches and inliers are over
        the primary registrations.
        """
        p = self.pairs
        consecutive = (self.pair_index[:, 1] - self.pair_index[:, 0] == 1) | (self.pair_index[:, 0] < 0)
        return {
            "level": self.level,
            "groups": len(self.groups),
            "pairs": len(p.ok),
            "failed_pairs": int((~p.ok[consecutive]).sum()),
            "failed_pair_indices": np.where(self.pair_index[:, 0] < 0, self.pair_index[:, 1],
                                            self.pair_index[:, 0])[consecutive & ~p.ok].tolist(),
            "extra_pairs_used": int(p.ok[~consecutive].sum()),
            "median_matches": float(np.median(p.matches[consecutive])) if consecutive.any() else 0.0,
            "median_inliers": float(np.median(p.inliers[consecutive])) if consecutive.any() else 0.0,
            "min_inliers": int(p.inliers[consecutive].min()) if consecutive.any() else 0,
            "rejected_keyframes": self.rejected_keyframes,
            "timings_s": self.timings_s,
        }


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
    from scipy.sparse import csr_matrix

    g = len(initial)
    use = pairs.ok & (pair_index[:, 0] != pair_index[:, 1])
    if g < 2 or not use.any():
        return initial
    a, b = pair_index[use, 0], pair_index[use, 1]
    gx, gy = np.meshgrid(np.linspace(0, width - 1, 3), np.linspace(0, height - 1, 3))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (9, 2) points of frame b
    mapped = geometry.apply(pairs.homographies[use], grid)  # (E, 9, 2) points of frame a
    weight = np.sqrt(np.maximum(pairs.inliers[use], 1) / max(np.median(pairs.inliers[use]), 1))[:, None, None]
    e = len(a)
    # Each keyframe is solved as a small update of its starting value, K_g = initial_g @ H(d_g):
    # the 8 parameters of d_g are all of order 1e-3 and well conditioned, whereas the
    # absolute parameters of keyframes far along a pan (hundreds of pixels) are not.
    rows = np.arange(e * 18).reshape(e, 9, 2)
    points_b = np.broadcast_to(grid, (e, 9, 2))

    def project(k: NDArray[np.float64], points: NDArray[np.float64]):
        """Map (E, 9, 2) points by (E, 3, 3) homographies; return them and d(point)/d(p1..p8)."""
        x, y = points[..., 0], points[..., 1]
        nx = k[:, None, 0, 0] * x + k[:, None, 0, 1] * y + k[:, None, 0, 2]
        ny = k[:, None, 1, 0] * x + k[:, None, 1, 1] * y + k[:, None, 1, 2]
        d = k[:, None, 2, 0] * x + k[:, None, 2, 1] * y + k[:, None, 2, 2]
        u, v = nx / d, ny / d
        zero = np.zeros_like(u)
        # p1..p8 of H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]] (paper Eq. 4)
        du = np.stack([x, zero, y, zero, np.ones_like(u), zero, -u * x, -u * y], axis=-1) / d[..., None]
        dv = np.stack([zero, x, zero, y, zero, np.ones_like(u), -v * x, -v * y], axis=-1) / d[..., None]
        return np.stack([u, v], axis=-1), np.stack([du, dv], axis=-2)  # (E, 9, 2), (E, 9, 2, 8)

    def point_jacobian(k: NDArray[np.float64], q: NDArray[np.float64]):
        """Map (E, 9, 2) points q by fixed (E, 3, 3) homographies; return them and d(out)/d(q)."""
        qh = np.concatenate([q, np.ones(q.shape[:-1] + (1,))], axis=-1)
        out = np.einsum("eij,epj->epi", k, qh)
        u = out[..., :2] / out[..., 2:3]
        jac = (k[:, None, :2, :2] - u[..., :, None] * k[:, None, 2:3, :2]) / out[..., 2:3, None]
        return u, jac  # (E, 9, 2), (E, 9, 2, 2)

    def updates(free: NDArray[np.float64]) -> NDArray[np.float64]:
        """(G, 3, 3) keyframe updates H(d_g), the gauge keyframe's the identity."""
        return geometry.homographies_from_params(np.concatenate([np.zeros((1, 8)), free.reshape(g - 1, 8)]))

    relative0 = np.linalg.inv(initial[a]) @ initial[b]  # (E, 3, 3) starting b-to-a maps

    def evaluate(free: NDArray[np.float64]):
        """Residuals in frame a's pixels, ``M x - inv(K_a) K_b x``, and their Jacobians.

        Measured in the frame's own pixels (as Brown and Lowe do), not on the panorama:
        there, shrinking every keyframe would shrink every residual, a degenerate
        direction the solver follows on long captures.
        """
        update = updates(free)
        y, dy = project(update[b], points_b)                # frame b after its update
        z, dz = point_jacobian(relative0, y)                # into frame a's starting pixels
        w = geometry.apply(np.linalg.inv(update[a]), z)     # undo frame a's update
        _, dh = project(update[a], w)                       # d proj(H_a w) / d(params of a)
        _, jw = point_jacobian(update[a], w)                # d proj(H_a w) / dw
        jw_inv = np.linalg.inv(jw)
        # H_a w = z: dw/dparams_a = -inv(jw) dh; dw/dz = inv(jw)
        residual = mapped - w
        ja = np.einsum("epij,epjk->epik", jw_inv, dh)
        jb = -np.einsum("epij,epjk,epkl->epil", jw_inv, dz, dy)
        return residual, ja, -jb

    def linearise(free: NDArray[np.float64]) -> tuple[NDArray[np.float64], csr_matrix]:
        residual, ja, jb = evaluate(free)
        blocks = [(ja * weight[..., None], a), (-jb * weight[..., None], b)]
        r = np.concatenate([np.repeat(rows[idx > 0].reshape(-1), 8) for _, idx in blocks])
        c = np.concatenate([(8 * (idx[idx > 0] - 1))[:, None, None, None] + np.arange(8)
                            + np.zeros((1, 9, 2, 1), np.int64) for _, idx in blocks]).reshape(-1)
        v = np.concatenate([jac[idx > 0].reshape(-1) for jac, idx in blocks])
        return (residual * weight).ravel(), csr_matrix((v, (r, c)), shape=(e * 18, (g - 1) * 8))

    return initial @ updates(robust_least_squares(linearise, np.zeros((g - 1) * 8)))


def robust_least_squares(linearise: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], Any]],
                         x0: NDArray[np.float64], *, f_scale: float = 1.0, max_iterations: int = 50,
                         tolerance: float = 1e-6) -> NDArray[np.float64]:
    """Minimise ``sum(rho(r_i(x)^2))`` with the soft-L1 loss by Levenberg-Marquardt on a sparse Jacobian.

    ``rho(z) = 2 (sqrt(1 + z / f^2) - 1) f^2`` (scipy's ``soft_l1``), handled by
    iteratively reweighted least squares: each step solves the damped, reweighted normal
    equations ``(J^T W J + lambda diag(J^T W J)) dx = -J^T W r`` with
    ``W = diag(1 / sqrt(1 + r^2 / f^2))`` by a direct factorisation
    (:func:`_solve_normal_equations`: banded Cholesky, else SuperLU). For pose graphs,
    whose normal matrix is banded, this is 3-4x faster than scipy's ``least_squares``
    with ``lsmr`` (which it replaced) and linear in the number of keyframes. Reference:
    Triggs et al., "Bundle Adjustment - A Modern Synthesis", 2000, Secs. 4.3 and 6.

    Args:
        linearise: ``linearise(x)`` returns the residuals ((R,) float64) and their
            (R, N) sparse Jacobian at ``x``.
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

    x = np.asarray(x0, np.float64)
    residual, jacobian = linearise(x)
    cost, damping = loss(residual), 1e-3
    for _ in range(max_iterations):
        w = 1 / np.sqrt(1 + (residual / f_scale) ** 2)
        weighted = jacobian.T.multiply(w).tocsr()
        normal, gradient = (weighted @ jacobian).tocoo(), weighted @ residual
        scale = np.maximum(normal.diagonal(), 1e-12)
        while True:
            step = -_solve_normal_equations(normal, damping * scale, gradient)
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


def _solve_normal_equations(normal: Any, damping: NDArray[np.float64], rhs: NDArray[np.float64],
                            max_band_bytes: float = 2 ** 28) -> NDArray[np.float64]:
    """Solve ``(N + diag(damping)) x = rhs`` for a sparse symmetric positive definite N (COO).

    A pose graph's unknowns are ordered in time and its pairs span a bounded offset, so N
    is banded: LAPACK's banded Cholesky (``solveh_banded``) costs ``n u^2`` for
    bandwidth u, several times faster than a general sparse LU. Wider bands (loop
    closures) fall back to SuperLU.
    """
    from scipy.linalg import LinAlgError, solveh_banded
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    n = len(rhs)
    upper = normal.col >= normal.row
    band = int((normal.col - normal.row).max(initial=0))
    if (band + 1) * n * 8 <= max_band_bytes:
        ab = np.zeros((band + 1, n))
        ab[band + normal.row[upper] - normal.col[upper], normal.col[upper]] = normal.data[upper]
        ab[band] += damping
        try:
            return solveh_banded(ab, rhs, check_finite=False)
        except LinAlgError:
            pass
    return spsolve((normal + diags(damping)).tocsc(), rhs)


def pairs_at_offsets(count: int, offsets: tuple[int, ...]) -> NDArray[np.int64]:
    """Return (P, 2) int64 pairs ``(g, g + k)`` of ``count`` merged frames for each offset k.

    Offset 1 (consecutive pairs) is always included, so the pairs chain all frames.
    """
    ks = sorted({1, *offsets})
    rows = [np.stack([np.arange(count - k), np.arange(k, count)], axis=1) for k in ks if k < count]
    return np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 2), np.int64)


def plausible(homographies: NDArray[np.float64], width: int, height: int,
              max_area_change: float = 2.0) -> NDArray[np.bool_]:
    """Flag homographies that could relate two frames of a continuous capture.

    A homography is implausible when it folds the frame (the warped corners are not a
    convex quadrilateral in the same orientation) or changes its area by more than a
    factor ``max_area_change``; such results come from spurious feature matches.

    Args:
        homographies: (P, 3, 3) float64.
        width: frame width in pixels.
        height: frame height in pixels.
        max_area_change: largest accepted area ratio (and inverse).

    Returns:
        (P,) bool.
    """
    q = geometry.apply(homographies, geometry.corners(width, height))  # (P, 4, 2)
    edge = np.roll(q, -1, axis=1) - q
    cross = edge[..., 0] * np.roll(edge, -1, axis=1)[..., 1] - edge[..., 1] * np.roll(edge, -1, axis=1)[..., 0]
    shoelace = q[..., 0] * np.roll(q[..., 1], -1, axis=1) - np.roll(q[..., 0], -1, axis=1) * q[..., 1]
    area = 0.5 * np.abs(np.sum(shoelace, axis=1))
    ratio = area / ((width - 1) * (height - 1))
    finite = np.all(np.isfinite(q), axis=(1, 2))
    return finite & np.all(cross > 0, axis=1) & (ratio < max_area_change) & (ratio > 1 / max_area_change)


def _concat(*parts: PairRegistrations) -> PairRegistrations:
    if not parts:
        return PairRegistrations(np.zeros((0, 3, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool))
    return PairRegistrations(*(np.concatenate([getattr(p, f) for p in parts])
                               for f in ("homographies", "matches", "inliers", "ok")))


def _take(regs: PairRegistrations, index: Any) -> PairRegistrations:
    return PairRegistrations(*(getattr(regs, f)[index] for f in ("homographies", "matches", "inliers", "ok")))


class _MergedRing:
    """Merged frames of the last ``capacity`` groups, group j in slot ``j % capacity``."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.frames: MergedFrames | None = None

    def put(self, index: NDArray[np.int64], merged: MergedFrames) -> None:
        if self.frames is None:
            shape = (self.capacity,) + merged.flux.shape[1:]
            self.frames = MergedFrames(*(np.zeros(shape, getattr(merged, f).dtype)
                                         for f in ("flux", "frames", "images", "masks")))
        slots = index % self.capacity
        for f in ("flux", "frames", "images", "masks"):
            getattr(self.frames, f)[slots] = getattr(merged, f)

    def register(self, locator: Locator, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                 width: int, height: int) -> PairRegistrations:
        """Register group pairs held in the ring; implausible results count as failed."""
        found = locator.register_pairs(self.frames, pairs % self.capacity, initial)
        return PairRegistrations(found.homographies, found.matches, found.inliers,
                                 found.ok & plausible(found.homographies, width, height))


def _overlapping(pairs: NDArray[np.int64], keyframes: NDArray[np.float64], width: int, height: int,
                 min_overlap: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Keep the pairs whose frames ``keyframes`` predict to overlap by ``min_overlap``; return them and their maps."""
    expected = np.linalg.inv(keyframes[pairs[:, 0]]) @ keyframes[pairs[:, 1]]
    centre = np.array([[(width - 1) / 2, (height - 1) / 2]])
    shift = geometry.apply(expected, centre)[:, 0] - centre
    overlap = np.clip(1 - np.abs(shift[:, 0]) / width, 0, 1) * np.clip(1 - np.abs(shift[:, 1]) / height, 0, 1)
    keep = overlap >= min_overlap
    return pairs[keep], expected[keep]


def locate_keyframes(locator: Locator, merge: Callable[[NDArray[np.int64]], MergedFrames],
                     current: NDArray[np.float64], pair_offsets: tuple[int, ...], width: int, height: int, *,
                     window: int = 32, min_overlap: float = 0.5, outlier_px: float = 1.0
                     ) -> tuple[NDArray[np.float64], NDArray[np.int64], PairRegistrations]:
    """Register merged frames pairwise and solve for the homographies of their reference frames.

    1. Consecutive pairs are registered and chained (:func:`chain_keyframes`), failed
       or implausible pairs bridged.
    2. For each offset k > 1, pairs ``(g - k, g)`` that the chain predicts to overlap by
       at least ``min_overlap`` are registered too.
    3. All plausible pairs are solved jointly (:func:`refine_keyframes`, robust loss);
       pairs whose corners disagree with that solution by more than
       ``max(outlier_px, 4 x median disagreement)`` are rejected and the graph is
       solved again. A wrong consecutive link is thereby outvoted by the longer pairs
       spanning it.

    Merged frames stream: ``merge`` is called on consecutive windows of ``window``
    groups and steps 1 and 2 run as they arrive (one ``register_pairs`` call per
    window), keeping only the merged frames that later pairs reach back to. Memory is
    thus bounded by ``2 x window + max(pair_offsets)`` merged frames whatever the
    capture length; the pose graph (step 3) holds only the pair homographies.

    Args:
        locator: the built locator.
        merge: ``merge(index)`` returns the merged frames of groups ``index`` ((K,)
            int64, consecutive and increasing).
        current: (G, 3, 3) float64 current homographies of the reference frames.
        pair_offsets: offsets k (1 is always used).
        width: frame width in pixels.
        height: frame height in pixels.
        window: groups merged and registered at a time.
        min_overlap: predicted overlap (fraction of the frame) needed to try a pair.
        outlier_px: smallest rejection threshold, in pixels (corner distance).

    Returns:
        ``(keyframes, pair_index, pairs)``: (G, 3, 3) float64 homographies, (P, 2)
        int64 pairs tried (the G - 1 consecutive pairs first) and their registrations
        (``ok`` False where failed or rejected).

    Raises:
        StageError: if every consecutive pair failed.
    """
    g = len(current)
    offsets = tuple(k for k in sorted(set(pair_offsets)) if 1 < k < g)
    windows = [np.arange(s, min(s + window, g)) for s in range(0, g, window)]
    ring = _MergedRing(min(g, 2 * window + max(offsets, default=0)))
    predicted = np.linalg.inv(current[:-1]) @ current[1:]
    chain_parts: list[PairRegistrations] = []
    extra_parts: list[tuple[NDArray[np.int64], PairRegistrations]] = []
    # One locator call per window: its consecutive pairs, and the longer pairs ending in the
    # previous window, whose overlap the chain up to there predicts. A frame is thus used
    # by consecutive calls only, and a locator's per-call cache describes it once.
    for w in range(len(windows) + 1):
        index, initial = [np.zeros((0, 2), np.int64)], [np.zeros((0, 3, 3))]
        if w < len(windows):
            new = windows[w]
            ring.put(new, merge(new))
            index.append(np.stack([new - 1, new], axis=1)[new > 0])
            initial.append(predicted[index[-1][:, 0]])
        n_chain = len(index[-1])
        if offsets and w > 0:
            done = windows[w - 1]
            chained = _concat(*chain_parts)
            try:
                so_far = chain_keyframes(current[:done[-1] + 1], chained)
            except StageError:  # every consecutive pair so far failed
                so_far = current[:done[-1] + 1]
            reach = np.concatenate([np.stack([done - k, done], axis=1)[done >= k] for k in offsets])
            reach, expected = _overlapping(reach, so_far, width, height, min_overlap)
            index.append(reach)
            initial.append(expected)
        index_all = np.concatenate(index)
        if not len(index_all):
            continue
        found = ring.register(locator, index_all, np.concatenate(initial), width, height)
        chain_parts.append(_take(found, slice(0, n_chain)))
        if len(index_all) > n_chain:
            extra_parts.append((index_all[n_chain:], _take(found, slice(n_chain, None))))
    chain_index = pairs_at_offsets(g, (1,))
    chain = _concat(*chain_parts)
    keyframes = chain_keyframes(current, chain)
    if not extra_parts:
        return keyframes, chain_index, chain
    extra = np.concatenate([index for index, _ in extra_parts])
    found = _concat(*(found for _, found in extra_parts))
    pair_index = np.concatenate([chain_index, extra])
    # Bridged consecutive pairs enter the solve with a token weight (one inlier) so
    # that the pose graph stays connected across registration failures.
    steps = np.linalg.inv(keyframes[:-1]) @ keyframes[1:]
    bridged = PairRegistrations(steps, chain.matches, np.where(chain.ok, chain.inliers, 1),
                                np.ones(len(steps), bool))
    graph = _concat(bridged, found)
    solved = refine_keyframes(keyframes, pair_index, graph, width, height)
    # A wrong registration that looked plausible disagrees with the joint solution of
    # all the others: drop such pairs and solve again.
    measured = _concat(chain, found).ok
    residual = _corner_disagreement(graph.homographies,
                                    np.linalg.inv(solved[pair_index[:, 0]]) @ solved[pair_index[:, 1]], width, height)
    limit = max(outlier_px, 4 * float(np.median(residual[measured]))) if measured.any() else np.inf
    outliers = measured & (residual > limit)
    if outliers.any():
        graph = PairRegistrations(graph.homographies, graph.matches, graph.inliers, graph.ok & ~outliers)
        solved = refine_keyframes(solved, pair_index, graph, width, height)
    pairs = _concat(chain, found)
    pairs = PairRegistrations(pairs.homographies, pairs.matches, pairs.inliers, pairs.ok & ~outliers)
    # Safety net: a joint solve that agrees with the trusted pairs worse than the chain
    # does (it did not converge) is discarded for the chain.
    trusted = pairs.ok
    if trusted.any():
        def disagreement(k: NDArray[np.float64]) -> float:
            relative = np.linalg.inv(k[pair_index[trusted, 0]]) @ k[pair_index[trusted, 1]]
            return float(np.median(_corner_disagreement(graph.homographies[trusted], relative, width, height)))

        if not np.isfinite(disagreement(solved)) or disagreement(solved) > disagreement(keyframes):
            solved = keyframes
    return solved, pair_index, pairs


def _stack(*parts: MergedFrames) -> MergedFrames:
    fields = ("flux", "frames", "images", "masks")
    return MergedFrames(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))


def _bridge(current: NDArray[np.float64], measured: NDArray[np.float64], ok: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Keyframes from measured ones where ``ok``, else by interpolating the frame-to-frame updates."""
    if ok.all():
        return measured
    update = geometry.params_from_homographies(np.linalg.inv(current) @ measured)
    idx = np.arange(len(ok))
    for k in range(8):
        update[~ok, k] = np.interp(idx[~ok], idx[ok], update[ok, k])
    return geometry.normalize(current @ geometry.homographies_from_params(update))


def locate_against_panorama(source: PhotonSource, merger: Merger, make_locator: Callable[[], Locator],
                            homographies: NDArray[np.float64], groups: Groups, *, min_frames: float,
                            template: Panorama | None = None, next_template: bool = False,
                            subbatch_px: float = 0.5, window: int = 16, executor: Executor | None = None,
                            progress: Callable[[int], None] | None = None
                            ) -> tuple[NDArray[np.float64], PairRegistrations, dict[str, int], Panorama | None]:
    """Register every merged frame of a level against the panorama of the current estimate.

    Frame-to-mosaic alignment (Szeliski, "Image Alignment and Stitching", 2006, Sec. 6.2;
    Sawhney and Kumar, 1999): once an estimate exists, every binary frame is warped onto
    one canvas (:func:`assemble_panorama`), and each merged frame is registered against
    that panorama resampled into its reference frame's grid. The panorama is a
    low-noise template averaged over the whole capture, so the registrations do not
    chain (no drift, no pose graph) and each group is registered once. Groups stream in
    windows: each window is merged, registered and dropped, so memory does not grow
    with the capture length. Each worker of ``executor`` builds its own locator.

    The template of the next level can be had without another pass over the photons:
    with ``next_template``, the merged frames are also accumulated onto the same canvas
    at their registered positions (a flux average weighted by frames).

    Args:
        source: the capture.
        merger: the built merger.
        make_locator: builds a locator (called once per worker thread).
        homographies: (T, 3, 3) float64 current frame-to-panorama homographies.
        groups: the level's G groups.
        min_frames: canvas pixels seen by fewer binary frames are not trusted.
        template: the panorama to register against, its ``homographies`` those of the
            current estimate on its canvas (None: assembled from every binary frame).
        next_template: also return the merged frames' panorama at the new keyframes.
        subbatch_px: sub-batch tolerance of an assembled template, in pixels.
        window: groups merged and registered per task.
        executor: runs windows in parallel (None: serially).
        progress: called with the number of groups done.

    Returns:
        ``(keyframes, registrations, cache_stats, next_template)``: (G, 3, 3) float64
        homographies of the reference frames (failed registrations bridged from their
        neighbours), the G registrations (merged frame pixels to panorama-view pixels),
        the locators' summed :meth:`cache_stats` (empty if they keep none), and the
        next template (its ``homographies`` still those of the input estimate) or None.

    Raises:
        StageError: if no merged frame could be registered.
    """
    import threading

    from .warping import WarpAccumulator

    executor = executor or SerialExecutor()
    if template is None:
        template = assemble_panorama(source, homographies, subbatch_px=subbatch_px, executor=executor)
    to_canvas = template.homographies[groups.reference]
    canvas_from_panorama = to_canvas[0] @ np.linalg.inv(homographies[groups.reference[0]])
    local = threading.local()
    built: list[tuple[Locator, WarpAccumulator, WarpAccumulator]] = []
    shape = template.flux.shape

    def run(index: NDArray[np.int64]) -> PairRegistrations:
        if not hasattr(local, "locator"):
            local.locator = make_locator()
            local.sums, local.weights = WarpAccumulator(*shape), WarpAccumulator(*shape)
            built.append((local.locator, local.sums, local.weights))
        merged = merger.merge(source, homographies, groups.select(index))
        views = panorama_views(template, to_canvas[index], source.height, source.width, min_frames)
        n = len(index)
        pairs = np.stack([np.arange(n), np.arange(n, 2 * n)], axis=1)
        result = local.locator.register_pairs(_stack(views, merged), pairs, np.repeat(np.eye(3)[None], n, axis=0))
        if next_template:
            placed = to_canvas[index] @ result.homographies
            for i in np.flatnonzero(result.ok):
                weight = np.where(merged.masks[i], merged.frames[i], 0).astype(np.float32)
                local.sums.add(np.nan_to_num(merged.flux[i]) * weight, 1, placed[i])
                local.weights.add(weight, 1, placed[i])
        if progress is not None:
            progress(n)
        return result

    windows = [np.arange(s, min(s + window, len(groups))) for s in range(0, len(groups), window)]
    parts = executor.map(run, windows)
    regs = _concat(*parts)
    ok = regs.ok & plausible(regs.homographies, source.width, source.height)
    if not ok.any():
        raise StageError("locator", "panorama", f"none of the {len(ok)} merged frames registered against "
                         "the panorama of the current estimate")
    regs = PairRegistrations(regs.homographies, regs.matches, regs.inliers, ok)
    current = homographies[groups.reference]
    keyframes = _bridge(current, geometry.normalize(current @ regs.homographies), ok)
    stats: dict[str, int] = {}
    for locator, _, _ in built:
        for key, value in (locator.cache_stats() if hasattr(locator, "cache_stats") else {}).items():
            stats[key] = stats.get(key, 0) + value
    following = None
    if next_template:
        sums, weights = built[0][1], built[0][2]
        for _, other_sums, other_weights in built[1:]:
            sums.merge(other_sums)
            weights.merge(other_weights)
        with np.errstate(divide="ignore", invalid="ignore"):
            flux = np.where(weights.counts > 0, sums.counts / weights.counts, np.nan).astype(np.float32)
        following = Panorama(flux=flux, frames=weights.counts, homographies=canvas_from_panorama @ homographies)
    return keyframes, regs, stats, following


def _guard_keyframes(current: NDArray[np.float64], solved: NDArray[np.float64], width: int,
                     height: int) -> tuple[NDArray[np.float64], int]:
    """Replace implausible keyframe updates by interpolation from their neighbours.

    The update of keyframe g is ``inv(current[g]) @ solved[g]`` (frame to frame); one
    that folds or rescales the frame (see :func:`plausible`) can only come from a
    degenerate solve, so its parameters are interpolated from the plausible ones.

    Returns:
        ``(keyframes, rejected)``: (G, 3, 3) float64 and the number replaced.

    Raises:
        StageError: if no keyframe update is plausible.
    """
    good = plausible(np.linalg.inv(current) @ solved, width, height)
    if not good.any():
        raise StageError("locator", "pose graph", "every keyframe update is implausible")
    return _bridge(current, solved, good), int((~good).sum())


def _corner_disagreement(a: NDArray[np.float64], b: NDArray[np.float64], width: int,
                         height: int) -> NDArray[np.float64]:
    """Largest corner distance in pixels between (P, 3, 3) homographies ``a`` and ``b``."""
    c = geometry.corners(width, height)
    return np.linalg.norm(geometry.apply(a, c) - geometry.apply(b, c), axis=-1).max(axis=-1)


def estimate_motion(
    source: PhotonSource,
    resampler: Resampler,
    merger: Merger,
    locator: Locator,
    interpolator: Interpolator,
    *,
    levels: int,
    group_size: int,
    pair_offsets: tuple[int, ...] = (1,),
    executor: Executor | None = None,
    refine_locator: Callable[[], Locator] | None = None,
    refine_subbatch_px: float = 0.5,
    keep_merged: bool = False,
    on_level: Callable[[LevelResult], None] | None = None,
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
    start_level: int = 1,
    initial: NDArray[np.float64] | None = None,
    template: Panorama | None = None,
) -> tuple[NDArray[np.float64], list[LevelResult]]:
    """Estimate a homography for every binary frame by stratified re-sampling.

    Each level: re-sample groups, merge them with the current homographies (relative to
    each group's reference frame), register consecutive merged frames, chain them into
    keyframe homographies, and interpolate the keyframe *corrections*
    ``K_g @ inv(H[ref_g])`` to every frame, so that detail resolved at earlier, denser
    levels is kept (at level 1, where ``H`` is the identity, this is the paper's plain
    interpolation of the keyframe homographies).

    Level 1 registers pairs of merged frames (consecutive, and at ``pair_offsets``) with
    ``locator`` and solves them jointly (:func:`locate_keyframes`). With
    ``refine_locator``, every later level registers each merged frame against the
    panorama of the current estimate instead (:func:`locate_against_panorama`): no
    chaining, one registration per group, groups streamed in windows; without it, later
    levels repeat level 1's pairwise scheme (the paper's).

    Args:
        source: the capture.
        resampler: the built resampler (groups of each level).
        merger: the built merger (virtual exposures).
        locator: the built locator of pairwise levels.
        interpolator: the built interpolator (homographies for every binary frame).
        levels: number of levels (>= 1).
        group_size: binary frames per group m.
        pair_offsets: register merged frames g and g + k for each k; (1,) is the
            paper's chain of consecutive pairs, more offsets feed :func:`refine_keyframes`.
        executor: runs independent groups in parallel (None: serially).
        refine_locator: builds the locator of levels >= 2 against the panorama (called
            once per worker thread); None: pairwise at every level.
        refine_subbatch_px: sub-batch tolerance (pixels) of those panoramas.
        keep_merged: keep each level's merged frames in its result (pairwise levels only).
        on_level: called with each finished level.
        progress: ``progress(description, total)`` returns an ``advance(n)`` callable.
        start_level: resume with this level (the result equals that of an uninterrupted run).
        initial: (T, 3, 3) float64 homographies after level ``start_level - 1`` (its
            :class:`LevelResult`'s, before the final gauge); None: identities.
        template: that level's :attr:`LevelResult.template`.

    Returns:
        ``(homographies, levels)``: (T, 3, 3) float64 frame-to-panorama homographies,
        where panorama coordinates are the pixel coordinates of the middle binary frame
        ``T // 2`` (its homography is the identity), and one :class:`LevelResult` per
        level (their homographies in the same coordinates).

    Raises:
        StageError: if a level cannot register any pair.
        ValueError: if the capture is too short for ``group_size``.
    """
    n = source.n_frames
    homographies = np.repeat(np.eye(3)[None], n, axis=0) if initial is None else np.array(initial, np.float64)
    results: list[LevelResult] = []
    # template: of the next level against the panorama, when already known
    for level in range(start_level, levels + 1):
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        try:
            groups = resampler.groups(n, group_size, level)
        except ValueError as exc:
            raise StageError("resampler", type(resampler).__name__, str(exc)) from None
        t1 = time.perf_counter()
        refs = groups.reference
        current = homographies[refs]
        merged, cache = None, None
        if level >= 2 and refine_locator is not None:
            advance = progress(f"level {level}: merge + locate", len(groups)) if progress else None
            try:
                keyframes, pairs, cache, template = locate_against_panorama(
                    source, merger, refine_locator, homographies, groups, min_frames=group_size,
                    template=template, next_template=level < levels, subbatch_px=refine_subbatch_px,
                    executor=executor, progress=advance)
            except StageError as err:
                raise StageError("locator", err.plugin, f"level {level}: {err.reason}") from None
            pair_index = np.stack([np.full(len(groups), -1), np.arange(len(groups))], axis=1).astype(np.int64)
            t2 = t1
        else:
            advance = progress(f"level {level}: merge + locate", len(groups)) if progress else None
            kept: list[MergedFrames] = []
            merge_s = 0.0

            def merge(index: NDArray[np.int64]) -> MergedFrames:
                nonlocal merge_s
                start = time.perf_counter()
                part = merger.merge(source, homographies, groups.select(index), progress=advance, executor=executor)
                merge_s += time.perf_counter() - start
                if keep_merged:
                    kept.append(part)
                return part

            locator.executor = executor
            try:
                keyframes, pair_index, pairs = locate_keyframes(locator, merge, current, pair_offsets,
                                                                source.width, source.height)
            except StageError as err:
                raise StageError("locator", type(locator).__name__, f"level {level}: {err.reason}") from None
            merged = _stack(*kept) if kept else None
            t2 = t1 + merge_s
        keyframes, rejected = _guard_keyframes(current, keyframes, source.width, source.height)
        t3 = time.perf_counter()
        correction = keyframes @ np.linalg.inv(current)
        previous = homographies
        updated = geometry.normalize(interpolator.interpolate(refs, correction, n, groups) @ homographies)
        if not plausible(np.linalg.inv(homographies) @ updated, source.width, source.height).all():
            raise StageError("interpolator", type(interpolator).__name__,
                             f"level {level}: the interpolated update folds or rescales some frames")
        homographies = updated
        if template is not None:  # the merged frames' panorama, on the updated estimate
            template = Panorama(template.flux, template.frames,
                                geometry.normalize(template.homographies @ np.linalg.inv(previous) @ updated))
        t4 = time.perf_counter()
        timings.update(resample=t1 - t0, merge=t2 - t1, locate=t3 - t2, interpolate=t4 - t3)
        result = LevelResult(level, groups, merged if keep_merged else None, pairs, pair_index, keyframes,
                             homographies, timings, rejected_keyframes=rejected, locator_cache=cache,
                             template=template)
        results.append(result)
        if on_level is not None:
            on_level(result)
    # Gauge: panorama coordinates are the pixel coordinates of the middle binary frame,
    # so the panorama has that frame's scale and perspective (as a stitching reference
    # image in the middle of the sequence keeps distortion low).
    middle = np.linalg.inv(homographies[n // 2])
    for result in results:
        result.homographies = geometry.normalize(middle @ result.homographies)
    return geometry.normalize(middle @ homographies), results
