"""Interpolator ``cubic-lk``: cubic splines through the 8 homography parameters.

Paper Sec. 4, "Interpolate", Eq. (4): ``H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]``
and each p_i is interpolated over time with a cubic spline (the extended Lucas-Kanade
parameterisation of Baker and Matthews, 2004).

What a keyframe homography measures matters (paper suppl. S.2): a locator registers a
*merged* frame, which shows the scene where the group's frames were on average. With
``measurement: exposure-average`` (the default) a cubic B-spline is fitted so that its
averages over each group's frames match the keyframes; with ``reference-frame`` the
spline passes through the keyframes at their reference frames (the paper's main text).

Keyframes are noisy measurements: a locator's error is largest in the parameters a
merged frame pins down least (rotation, zoom and perspective, p1-p4, p7, p8), while the
camera's translation (p5, p6) may vibrate fast. With ``smoothness: auto`` (the default)
each parameter gets its own second-difference penalty, chosen by generalised
cross-validation (Craven and Wahba, "Smoothing noisy data with spline functions",
Numerische Mathematik 31, 1979): a parameter that the keyframes measure as noise is
smoothed until its residuals look like noise, one that carries motion keeps it.
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


class CubicLKConfig(InterpolatorConfig):
    """Cubic splines on p1..p8 of the keyframe homographies (paper Eq. 4)."""

    plugin: Literal["cubic-lk"] = "cubic-lk"
    measurement: Literal["exposure-average", "reference-frame"] = "exposure-average"
    """What a keyframe homography stands for: the mean over its group's frames (a
    least-squares B-spline whose group averages match the keyframes, knots every
    max(keyframe spacing, m/2) frames), or the pose of the reference frame itself (an
    interpolating not-a-knot spline, the paper's main text)."""
    smoothness: Annotated[float, Field(ge=0)] | Literal["auto"] = "auto"
    """exposure-average: weight of the second-difference penalty on spline coefficients,
    relative to the data term (it settles coefficients the groups do not pin down); or
    ``auto``: per parameter, the weight in [1e-3, 1e4] that minimises the generalised
    cross-validation score (noisy parameters are smoothed more)."""
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

        lengths = (groups.stop - groups.start).astype(np.float64)
        spacing = float(np.median(np.diff(groups.reference))) if len(groups) > 1 else float(n_frames)
        step = max(spacing, float(np.median(lengths)) / 2, 1.0)
        count = max(int(np.ceil(n_frames / step)), 1)
        inner = np.linspace(-0.5, n_frames - 0.5, count + 1)  # frame t covers [t-0.5, t+0.5]
        d = inner[1] - inner[0]
        knots = np.concatenate([inner[0] - d * np.arange(3, 0, -1), inner, inner[-1] + d * np.arange(1, 4)])
        n_basis = len(knots) - 4
        integral = BSpline(knots, np.eye(n_basis), 3).antiderivative()
        lo, hi = groups.start - 0.5, groups.stop - 0.5
        design = (integral(hi) - integral(lo)) / lengths[:, None]  # (G, K) group means
        second = np.diff(np.eye(n_basis), 2, axis=0)
        gram, penalty = design.T @ design, second.T @ second
        scale = np.trace(gram) / n_basis
        if self.config.smoothness == "auto":
            coef = _gcv_coefficients(design, gram, penalty * scale, params)
        else:
            coef = np.linalg.solve(gram + self.config.smoothness * scale * penalty, design.T @ params)
        return BSpline(knots, coef, 3)(np.arange(n_frames, dtype=np.float64))


AUTO_SMOOTHNESS = np.logspace(-3, 4, 29)
"""Penalty weights ``smoothness: auto`` chooses from (relative to the data term)."""


def _gcv_coefficients(design: NDArray[np.float64], gram: NDArray[np.float64], penalty: NDArray[np.float64],
                      params: NDArray[np.float64]) -> NDArray[np.float64]:
    """Penalised least-squares coefficients, one penalty weight per parameter chosen by GCV.

    Minimises ``|design c - y|^2 + lam c' penalty c`` for each column y of ``params``,
    with ``lam`` from :data:`AUTO_SMOOTHNESS` minimising ``G |y - A y|^2 / (G - tr A)^2``
    (A the hat matrix; Craven and Wahba 1979). One generalised eigen-decomposition of
    (gram, penalty) serves every weight (Demmler-Reinsch basis).

    Args:
        design: (G, K) float64 group means of the K B-spline basis functions.
        gram: (K, K) ``design' design``.
        penalty: (K, K) positive semi-definite second-difference penalty.
        params: (G, 8) float64 keyframe parameters.

    Returns:
        (K, 8) float64 spline coefficients.
    """
    from scipy.linalg import eigh

    n_groups, n_basis = design.shape
    ridge = 1e-9 * np.trace(gram) / n_basis * np.eye(n_basis)  # basis functions no group covers
    gamma, basis = eigh(penalty, gram + ridge)  # basis' gram basis = I, basis' penalty basis = diag(gamma)
    gamma = np.maximum(gamma, 0)
    projected = basis.T @ (design.T @ params)  # (K, 8)
    fitted_basis = design @ basis  # (G, K)
    best = np.full(params.shape[1], np.inf)
    coef = np.zeros((n_basis, params.shape[1]))
    for lam in AUTO_SMOOTHNESS:
        shrink = 1 / (1 + lam * gamma)
        dof = shrink.sum()
        if dof >= n_groups - 0.5:
            continue
        weights = projected * shrink[:, None]
        score = n_groups * ((params - fitted_basis @ weights) ** 2).sum(axis=0) / (n_groups - dof) ** 2
        better = score < best
        best[better] = score[better]
        coef[:, better] = (basis @ weights)[:, better]
    if not np.isfinite(best).all():  # fewer groups than the spline's degrees of freedom: the least penalty
        lam = AUTO_SMOOTHNESS[0]
        missing = ~np.isfinite(best)
        coef[:, missing] = np.linalg.solve(gram + lam * penalty, design.T @ params[:, missing])
    return coef


@hookimpl
def photonpano_register_interpolators() -> list[type[InterpolatorConfig]]:
    """Register ``cubic-lk``."""
    return [CubicLKConfig]
