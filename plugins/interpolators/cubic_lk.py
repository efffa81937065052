"""Interpolator ``cubic-lk``: cubic splines through the 8 homography parameters.

Paper Sec. 4, "Interpolate", Eq. (4): ``H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]``
and each p_i is interpolated over time with a cubic spline (the extended Lucas-Kanade
parameterisation of Baker and Matthews, 2004).

What a keyframe homography measures matters (paper suppl. S.2): a locator registers a
*merged* frame, which shows the scene where the group's frames were on average. With
``measurement: exposure-average`` (the default) a cubic B-spline is fitted so that its
averages over each group's frames match the keyframes, with a roughness penalty whose
weight for the frame's shape is chosen by cross-validation (``shape_smoothness: auto``);
with ``reference-frame`` the spline passes through the keyframes at their reference
frames (the paper's main text).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.geometry import homographies_from_params, params_from_homographies
from photonpano.stages import Groups, Interpolator, InterpolatorConfig
from photonpano.types import check_shape
from pydantic import Field

SHIFT = [4, 5]
"""Columns of ``p5, p6`` (translation) in the (N, 8) parameters of :func:`params_from_homographies`."""
SHAPE = [0, 1, 2, 3, 6, 7]
"""Columns of ``p1..p4, p7, p8`` (the linear part and perspective)."""
NOISE_FLOOR = np.array([2e-5, 2e-5, 2e-5, 2e-5, 0.01, 0.01, 4e-8, 4e-8])
"""Smallest robust standard deviation of each of p1..p8 in the outlier test: 0.01 px of
shift, and shapes that move a point 250 px from the centre by about 0.005 px."""


class CubicLKConfig(InterpolatorConfig):
    """Cubic splines on p1..p8 of the keyframe homographies (paper Eq. 4)."""

    plugin: Literal["cubic-lk"] = "cubic-lk"
    measurement: Literal["exposure-average", "reference-frame"] = "exposure-average"
    """What a keyframe homography stands for: the mean over its group's frames (a
    least-squares B-spline whose group averages match the keyframes, knots every
    max(keyframe spacing, m/2) frames), or the pose of the reference frame itself (an
    interpolating not-a-knot spline, the paper's main text)."""
    smoothness: Annotated[float, Field(ge=0)] = 1e-3
    """exposure-average: weight of the second-difference penalty on the spline
    coefficients of ``p5, p6`` (the frame centre's position, see below), relative to the
    data term; it settles coefficients the groups do not pin down. A camera's position
    changes fast (a 30 or 45 Hz vibration), and a stiffer spline biases it: 1e-2 raised the
    evaluation suite's RMSE (geometric mean +8 %; a 45 Hz vibration 0.037 -> 0.071 px, a
    120 Hz lamp over half the scene 0.037 -> 0.098)."""
    shape_smoothness: Annotated[float, Field(ge=0)] | Literal["auto"] = "auto"
    """exposure-average: the same weight for ``p1..p4, p7, p8``, the frame's shape
    (rotation, scale, shear, perspective; the level loop hands the interpolator poses
    about the frame centre, :func:`photonpano.levels.estimate_motion`). ``auto``: chosen
    per level and parameter by blocked cross-validation (:func:`_cross_validate`): a
    merged frame pins its shape far less precisely than its position, and the shape of a
    pan does not change at all, so where the held-out keyframes allow it the shape is a
    nearly straight line over the capture, while a camera that rolls, zooms or shakes by
    turning keeps a supple one. Against the fixed weight 1 of before (evaluation suite,
    ``benchmarks/suite.py``): RMSE animal_chelsea/base 0.052 -> 0.030 px,
    highcontrast_sunset/base 0.121 -> 0.070, interior_room/base 0.077 -> 0.034, rotation
    + zoom foliage_dandelions 0.048 -> 0.040, a camera shaking by turning (city_madison,
    ``vibration_model: rotation``) 0.073 -> 0.071. A number: that weight at every level."""
    outlier_threshold: Annotated[float, Field(gt=0)] | None = 2.0
    """exposure-average: keyframes that disagree with the fit by more than this many robust
    standard deviations are down-weighted (Huber's M-estimator, see :func:`_huber_fit`): a
    registration pulled by a passing object no longer bends the whole smoothed stretch
    around it. Measured (20 000 frames, a disc of radius 30 px crossing at 0.08 px/frame):
    highcontrast_hubble 0.233 -> 0.123 px, objects_coffee 0.170 -> 0.166; static suite
    captures within 0.001 px but the clock 0.609 -> 0.587 and the dark outdoor scene 0.938
    -> 0.902. None: plain least squares."""
    extrapolate: Literal["linear", "constant"] = "linear"
    """reference-frame: beyond the first and last keyframe, continue the end tangent
    (linear) or hold the end value (constant)."""

    def build(self) -> CubicLKInterpolator:
        """Return the interpolator."""
        return CubicLKInterpolator(self)


class CubicLKInterpolator(Interpolator):
    """Cubic-spline interpolation of homography parameters (see :class:`CubicLKConfig`)."""

    def __init__(self, config: CubicLKConfig) -> None:
        self.config = config

    def warm_up(self) -> None:
        """Import ``scipy.interpolate`` (0.17 s; see :meth:`Interpolator.warm_up`)."""
        import scipy.interpolate  # noqa: F401

    def interpolate(self, keyframes: NDArray[np.int64], homographies: NDArray[np.float64],
                    n_frames: int, groups: Groups | None = None) -> NDArray[np.float64]:
        """Interpolate to every frame (see :meth:`Interpolator.interpolate`).

        Raises:
            ValueError: if keyframes are empty, not strictly increasing or mismatched.
        """
        g = check_shape(keyframes, "G", name="keyframes")["G"]
        check_shape(homographies, "G 3 3", name="homographies", G=g)
        if g == 0 or np.any(np.diff(keyframes) <= 0):
            raise ValueError("keyframes must be non-empty and strictly increasing")
        params = params_from_homographies(homographies)
        if g == 1:
            return homographies_from_params(np.repeat(params, n_frames, axis=0))
        if self.config.measurement == "exposure-average" and groups is not None:
            return homographies_from_params(self._fit_exposures(params, groups, n_frames))
        return homographies_from_params(self._through_keyframes(keyframes, params, n_frames))

    def _through_keyframes(self, keyframes, params, n_frames):
        from scipy.interpolate import CubicSpline

        x = keyframes.astype(np.float64)
        t = np.arange(n_frames, dtype=np.float64)
        spline = CubicSpline(x, params, axis=0, bc_type="not-a-knot", extrapolate=False)
        out = np.empty((n_frames, 8))
        inside = (t >= x[0]) & (t <= x[-1])
        out[inside] = spline(t[inside])
        slope_lo, slope_hi = spline(x[0], 1), spline(x[-1], 1)
        if self.config.extrapolate == "constant":
            slope_lo = slope_hi = np.zeros(8)
        lo, hi = t < x[0], t > x[-1]
        out[lo] = params[0] + (t[lo, None] - x[0]) * slope_lo
        out[hi] = params[-1] + (t[hi, None] - x[-1]) * slope_hi
        return out

    def _fit_exposures(self, params, groups: Groups, n_frames: int):
        """Least-squares cubic B-spline whose mean over each group equals its keyframe."""
        from scipy.interpolate import BSpline

        knots, design = exposure_design(groups, n_frames)
        n_basis = design.n_basis
        shape: float | NDArray[np.float64]
        if self.config.shape_smoothness == "auto":
            folds = _folds(groups)
            shape = SHAPE_DEFAULT if folds is None else _cross_validate(design, params[:, SHAPE], *folds)
        else:
            shape = self.config.shape_smoothness
        coef = np.empty((n_basis, params.shape[1]))
        for columns, weight in ((SHIFT, self.config.smoothness), (SHAPE, shape)):
            weights = np.broadcast_to(np.asarray(weight, np.float64), (len(columns),))
            coef[:, columns] = _huber_fit(design, params[:, columns], weights, self.config.outlier_threshold,
                                          NOISE_FLOOR[columns])
        return BSpline(knots, coef, 3)(np.arange(n_frames, dtype=np.float64))


def exposure_design(groups: Groups, n_frames: int) -> tuple[NDArray[np.float64], "_Design"]:
    """The cubic B-spline basis of an exposure-average fit and its (banded) group-mean design.

    Knots are uniform over ``[-0.5, n_frames - 0.5]`` (frame ``t`` covers ``[t - 0.5, t + 0.5]``),
    one per ``max(median reference spacing, median group length / 2, 1)`` frames. Row ``g`` of
    the design is the mean of each basis function over group ``g``'s frames.

    Args:
        groups: the level's groups (``start``, ``stop``, ``reference`` in frames).
        n_frames: frames in the capture.

    Returns:
        ``(knots, design)``: (K + 4,) float64 knots in frames and the (G, K) :class:`_Design`.
        Basis function ``j`` is zero outside ``[knots[j], knots[j + 4]]``, so its mean over a
        group that misses that interval is exactly 0 (not the rounding of two equal
        integrals, which spread every row over the whole basis: a level of 235 groups and
        121 basis functions then had a band of 121, its normal equations took 20 ms instead of
        0.03, and a 20 000-frame run spent a second in them).
    """
    from scipy.interpolate import BSpline

    lengths = (groups.stop - groups.start).astype(np.float64)
    spacing = float(np.median(np.diff(groups.reference))) if len(groups) > 1 else float(n_frames)
    step = max(spacing, float(np.median(lengths)) / 2, 1.0)
    count = max(int(np.ceil(n_frames / step)), 1)
    inner = np.linspace(-0.5, n_frames - 0.5, count + 1)
    d = inner[1] - inner[0]
    knots = np.concatenate([inner[0] - d * np.arange(3, 0, -1), inner, inner[-1] + d * np.arange(1, 4)])
    n_basis = len(knots) - 4
    integral = BSpline(knots, np.eye(n_basis), 3).antiderivative()
    lo, hi = groups.start - 0.5, groups.stop - 0.5
    means = (integral(hi) - integral(lo)) / lengths[:, None]
    means[(hi[:, None] <= knots[None, :n_basis]) | (lo[:, None] >= knots[None, 4:])] = 0.0
    return knots, _Design(means)


class _Design:
    """The (G, K) design of a spline fit to group means, kept as its band, with banded normal equations.

    Row g is non-zero only on the few basis functions whose support meets group g, so the
    normal equations ``design' W design + weight * penalty`` are banded and solved in
    O(K) (:func:`scipy.linalg.solveh_banded`) rather than O(K^3): a 100 000-frame capture
    has about a thousand coefficients.

    Args:
        dense: (G, K) float64 group means of the K basis functions.
    """

    def __init__(self, dense: NDArray[np.float64]) -> None:
        g, k = dense.shape
        nonzero = dense != 0
        first = nonzero.argmax(axis=1)
        last = k - nonzero[:, ::-1].argmax(axis=1)
        self.width = min(max(int((last - first).max()), 3), k)  # >= 3: the second-difference penalty's band
        self.first = np.minimum(first, k - self.width)
        self.values = np.take_along_axis(dense, self.first[:, None] + np.arange(self.width), axis=1)
        self.n_basis = k
        penalty = _Design.__new__(_Design)  # second differences of the coefficients
        penalty.first, penalty.width, penalty.n_basis = np.arange(max(k - 2, 0)), 3, k
        penalty.values = np.tile([1.0, -2.0, 1.0], (max(k - 2, 0), 1))
        # relative to the data term: weight 1 balances the penalty against an average row
        self.penalty = penalty.normal(np.ones(max(k - 2, 0)), self.width) * (np.sum(self.values ** 2) / k)

    def __len__(self) -> int:
        return len(self.first)

    def take(self, rows: NDArray[np.bool_]) -> "_Design":
        """The design of some rows (same basis, same penalty)."""
        out = _Design.__new__(_Design)
        out.first, out.values, out.width, out.n_basis, out.penalty = (
            self.first[rows], self.values[rows], self.width, self.n_basis, self.penalty)
        return out

    def normal(self, weights: NDArray[np.float64], width: int) -> NDArray[np.float64]:
        """``design' diag(weights) design`` in the upper banded form of ``solveh_banded`` with ``width - 1`` bands."""
        bands = np.zeros((width, self.n_basis))
        for i in range(self.width):
            for j in range(i, self.width):
                np.add.at(bands[width - 1 + i - j], self.first + j, weights * self.values[:, i] * self.values[:, j])
        return bands

    def transpose_times(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """``design' values`` for (G, P) values: (K, P)."""
        out = np.zeros((self.n_basis, values.shape[1]))
        for j in range(self.width):
            np.add.at(out, self.first + j, self.values[:, j, None] * values)
        return out

    def times(self, coef: NDArray[np.float64]) -> NDArray[np.float64]:
        """``design coef`` for (K, P) coefficients: (G, P)."""
        return np.einsum("gj,gjp->gp", self.values, coef[self.first[:, None] + np.arange(self.width)])

    def solve(self, normal: NDArray[np.float64], weight: float, right: NDArray[np.float64]) -> NDArray[np.float64]:
        """Coefficients of ``(normal + weight * penalty) c = right`` (``normal`` from :meth:`normal`)."""
        from scipy.linalg import solveh_banded

        return np.asarray(solveh_banded(normal + weight * self.penalty, right), np.float64)


SHAPE_DEFAULT = 1.0
"""``shape_smoothness: auto`` where a level has too few groups to cross-validate."""

SMOOTHNESS_GRID = 10.0 ** np.arange(-3, 9)
"""The weights ``shape_smoothness: auto`` chooses from (relative to the data term)."""


def _folds(groups: Groups, count: int = 5) -> tuple[list[NDArray[np.int64]], NDArray[np.int64]] | None:
    """Held-out keyframes of a blocked cross-validation, or None for too few groups.

    Keyframes are cut into contiguous blocks spanning twice the median group length, and
    the blocks dealt to ``count`` folds in turn: a held-out keyframe then shares almost
    no photons with the keyframes fitted (groups overlap, and neighbours' registration
    errors are correlated; the h-block cross-validation of Burman, Chow and Nolan,
    Biometrika 81, 1994).

    Returns:
        ``(folds, blocks)``: ``count`` (n_k,) int64 arrays of keyframe indices, and the
        (G,) int64 block of each keyframe; None when there are fewer than two blocks per
        fold.
    """
    g = len(groups)
    if g < 2:
        return None
    spacing = max(float(np.median(np.diff(groups.reference))), 1.0)
    block = max(1, int(np.ceil(2 * float(np.median(groups.stop - groups.start)) / spacing)))
    blocks = np.arange(g) // block
    if blocks[-1] + 1 < 2 * count:
        return None
    return [np.flatnonzero(blocks % count == k) for k in range(count)], blocks


def _cross_validate(design: _Design, values: NDArray[np.float64], folds: list[NDArray[np.int64]],
                    blocks: NDArray[np.int64]) -> NDArray[np.float64]:
    """Each column's smoothness weight from :data:`SMOOTHNESS_GRID`, by blocked cross-validation.

    For every weight, the penalised fit of the other folds (:func:`_folds`) predicts each
    held-out keyframe. Of the weights whose mean squared prediction error is within one
    standard error of the least, the largest wins (the one-standard-error rule: Breiman
    et al., *Classification and Regression Trees*, 1984, Sec. 3.4.3; Hastie, Tibshirani
    and Friedman, *The Elements of Statistical Learning*, 2009, Sec. 7.10), the standard
    error taken over the blocks, whose errors are nearly independent. A camera whose
    rotation, scale and perspective do not change (a pan) thus gets the stiffest spline,
    one that turns, zooms or shakes by turning a supple one.

    Args:
        design: the fit's design (:class:`_Design`).
        values: (G, P) float64 keyframe parameters.
        folds: held-out keyframe indices of each fold.
        blocks: (G,) int64 block of each keyframe.

    Returns:
        (P,) float64 weights.
    """
    errors = np.zeros((len(SMOOTHNESS_GRID),) + values.shape)  # (weights, G, P) squared prediction errors
    for held in folds:
        kept = np.ones(len(values), bool)
        kept[held] = False
        fitted, predicted = design.take(kept), design.take(~kept)
        normal = fitted.normal(np.ones(int(kept.sum())), design.width)
        right = fitted.transpose_times(values[kept])
        for i, weight in enumerate(SMOOTHNESS_GRID):
            errors[i, held] = (predicted.times(design.solve(normal, weight, right)) - values[held]) ** 2
    per_block = np.zeros((blocks[-1] + 1, len(SMOOTHNESS_GRID), values.shape[1]))
    np.add.at(per_block, blocks, errors.transpose(1, 0, 2))
    per_block = per_block.transpose(1, 0, 2)  # (weights, blocks, P) summed squared errors
    n_blocks = per_block.shape[1]
    mean = per_block.mean(axis=1)  # (weights, P)
    best = np.argmin(mean, axis=0)
    columns = np.arange(values.shape[1])
    error = per_block[best, :, columns].std(axis=1, ddof=1) / np.sqrt(n_blocks)  # (P,)
    within = mean <= (mean[best, columns] + error)[None]
    chosen = np.array([np.flatnonzero(within[:, j]).max() for j in columns])
    return np.asarray(SMOOTHNESS_GRID[chosen], np.float64)


def _huber_fit(design: _Design, values: NDArray[np.float64], weights: NDArray[np.float64], threshold: float | None,
               floor: NDArray[np.float64], iterations: int = 4) -> NDArray[np.float64]:
    """Penalised least squares ``min sum_g w_g |design_g c_j - values_gj|^2 + weights_j c_j' penalty c_j``.

    Huber's M-estimator by iteratively reweighted least squares (Huber, "Robust estimation
    of a location parameter", 1964; Holland and Welsch, 1977): a keyframe whose residual,
    the root mean square over the columns of its residuals in units of each column's robust
    standard deviation (1.4826 x the median absolute deviation, at least ``floor``), exceeds ``threshold`` gets
    the weight ``threshold / residual``. The penalty is scaled by the mean weight, so
    that down-weighting does not shift the balance between data and smoothness.

    Args:
        design: the fit's design (:class:`_Design`, with its roughness penalty).
        values: (G, P) float64 keyframe parameters.
        weights: (P,) float64 smoothness weight of each column.
        threshold: Huber threshold; None: plain least squares.
        floor: (P,) float64 smallest standard deviation of each column (a fit closer than
            registration noise has no outliers).
        iterations: reweighting passes.

    Returns:
        (K, P) float64 spline coefficients.
    """
    keyframe_weights = np.ones(len(values))
    coef = np.empty((design.n_basis, values.shape[1]))
    for _ in range(iterations if threshold is not None else 1):
        normal = design.normal(keyframe_weights, design.width)
        right = design.transpose_times(values * keyframe_weights[:, None])
        scale = float(np.mean(keyframe_weights))
        for weight in np.unique(weights):  # one factorisation per distinct weight
            columns = np.flatnonzero(weights == weight)
            coef[:, columns] = design.solve(normal, scale * weight, right[:, columns])
        if threshold is None:
            break
        residual = design.times(coef) - values
        spread = np.maximum(1.4826 * np.median(np.abs(residual - np.median(residual, axis=0)), axis=0), floor)
        size = np.sqrt(np.mean((residual / spread) ** 2, axis=1))
        keyframe_weights = np.minimum(1.0, threshold / np.maximum(size, 1e-300))
    return coef


@hookimpl
def photonpano_register_interpolators() -> list[type[InterpolatorConfig]]:
    """Register ``cubic-lk``."""
    return [CubicLKConfig]
