"""Plausibility guards: registrations and keyframe updates that fold or rescale a frame.

A homography between frames of one capture cannot turn a frame inside out or change its
area by a large factor; such a result comes from a failed registration or a degenerate
solve, and is bridged from its neighbours instead (:func:`bridge`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .errors import StageError

__all__ = ["plausible", "bridge", "guard_keyframes"]


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


def bridge(current: NDArray[np.float64], measured: NDArray[np.float64], ok: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Take measured keyframes where ``ok``, and interpolate the others' updates from their neighbours.

    The update of keyframe g is ``inv(current[g]) @ measured[g]``; where ``ok`` is False
    its eight parameters (p1..p8) are linearly interpolated over the group index.

    Args:
        current: (G, 3, 3) float64 keyframe homographies before the level.
        measured: (G, 3, 3) float64 measured keyframe homographies.
        ok: (G,) bool measurements to keep (at least one True).

    Returns:
        (G, 3, 3) float64 keyframe homographies.
    """
    if ok.all():
        return measured
    update = geometry.params_from_homographies(np.linalg.inv(current) @ measured)
    idx = np.arange(len(ok))
    for k in range(8):
        update[~ok, k] = np.interp(idx[~ok], idx[ok], update[ok, k])
    return geometry.normalize(current @ geometry.homographies_from_params(update))


def guard_keyframes(current: NDArray[np.float64], solved: NDArray[np.float64], width: int,
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
    return bridge(current, solved, good), int((~good).sum())
