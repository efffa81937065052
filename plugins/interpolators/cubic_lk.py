"""Interpolator ``cubic-lk``: cubic interpolation of the 8 homography parameters.

Paper Sec. 4, "Interpolate", Eq. (4): ``H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]``
and each p_i is interpolated over time with a cubic spline (the extended Lucas-Kanade
parameterisation of Baker and Matthews, 2004).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

from photonpano import hookimpl
from photonpano.geometry import homographies_from_params, params_from_homographies
from photonpano.stages import Interpolator, InterpolatorConfig
from photonpano.types import check_shape


class CubicLKConfig(InterpolatorConfig):
    """Cubic spline through p1..p8 of the keyframe homographies."""

    plugin: Literal["cubic-lk"] = "cubic-lk"
    extrapolate: Literal["linear", "constant"] = "linear"
    """Beyond the first and last keyframe: continue the spline's end tangent (linear)
    or hold the end value (constant)."""

    def build(self) -> CubicLKInterpolator:
        """Return the interpolator."""
        return CubicLKInterpolator(self)


class CubicLKInterpolator(Interpolator):
    """Not-a-knot cubic spline inside the keyframes, ``extrapolate`` outside."""

    def __init__(self, config: CubicLKConfig) -> None:
        self.config = config

    def interpolate(self, keyframes: NDArray[np.int64], homographies: NDArray[np.float64],
                    n_frames: int) -> NDArray[np.float64]:
        """Interpolate to every frame (see :meth:`Interpolator.interpolate`).

        With one keyframe every frame gets its homography; with two the parameters are
        interpolated linearly, with three quadratically, with more by a not-a-knot
        cubic spline.

        Raises:
            ValueError: if keyframes are empty, not strictly increasing or mismatched.
        """
        from scipy.interpolate import CubicSpline

        g = check_shape(keyframes, "G", name="keyframes")["G"]
        check_shape(homographies, "G 3 3", name="homographies", G=g)
        if g == 0 or np.any(np.diff(keyframes) <= 0):
            raise ValueError("keyframes must be non-empty and strictly increasing")
        params = params_from_homographies(homographies)
        t = np.arange(n_frames, dtype=np.float64)
        if g == 1:
            return homographies_from_params(np.repeat(params, n_frames, axis=0))
        x = keyframes.astype(np.float64)
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
        return homographies_from_params(out)


@hookimpl
def photonpano_register_interpolators() -> list[type[InterpolatorConfig]]:
    """Register ``cubic-lk``."""
    return [CubicLKConfig]
