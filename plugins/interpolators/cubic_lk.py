"""Interpolator ``cubic-lk``: cubic splines through the 8 homography parameters.

Paper Sec. 4, "Interpolate", Eq. (4): ``H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]``
and each p_i is interpolated over time with a cubic spline (the extended Lucas-Kanade
parameterisation of Baker and Matthews, 2004).

What a keyframe homography measures matters (paper suppl. S.2): a locator registers a
*merged* frame, which shows the scene where the group's frames were on average. With
``measurement: exposure-average`` (the default) a cubic B-spline is fitted so that its
averages over each group's frames match the keyframes; with ``reference-frame`` the
spline passes through the keyframes at their reference frames (the paper's main text).
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
    smoothness: Annotated[float, Field(ge=0)] = 1e-3
    """exposure-average: weight of the second-difference penalty on spline coefficients,
    relative to the data term; it settles coefficients the groups do not pin down."""
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
        scale = np.trace(design.T @ design) / n_basis
        lhs = design.T @ design + self.config.smoothness * scale * second.T @ second
        coef = np.linalg.solve(lhs, design.T @ params)
        return BSpline(knots, coef, 3)(np.arange(n_frames, dtype=np.float64))


@hookimpl
def photonpano_register_interpolators() -> list[type[InterpolatorConfig]]:
    """Register ``cubic-lk``."""
    return [CubicLKConfig]
