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

__all__ = ["plausible", "bridge", "guard_keyframes", "agrees_with_neighbours"]


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
    # one contiguous row per matrix entry: the level loop checks one homography per binary
    # frame (100 000: 9 ms, against 28 ms through (P, 4, 2) corner arrays)
    h = np.asarray(homographies, dtype=np.float64).reshape(-1, 9).T.copy()
    qx, qy = [], []
    for x, y in geometry.corners(width, height):  # clockwise
        den = h[6] * x + h[7] * y + h[8]
        qx.append((h[0] * x + h[1] * y + h[2]) / den)
        qy.append((h[3] * x + h[4] * y + h[5]) / den)
    ok = np.ones(h.shape[1], bool)
    twice_area = np.zeros(h.shape[1])
    for k in range(4):
        i, j = (k + 1) % 4, (k + 2) % 4
        ok &= np.isfinite(qx[k]) & np.isfinite(qy[k])
        ok &= (qx[i] - qx[k]) * (qy[j] - qy[i]) - (qy[i] - qy[k]) * (qx[j] - qx[i]) > 0  # turns the same way
        twice_area += qx[k] * qy[i] - qx[i] * qy[k]  # shoelace
    ratio = 0.5 * np.abs(twice_area) / ((width - 1) * (height - 1))
    return ok & (ratio < max_area_change) & (ratio > 1 / max_area_change)


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
    degenerate solve, so its parameters are interpolated from the plausible ones, unless
    it agrees with its neighbours' updates (:func:`agrees_with_neighbours`). At level 1
    the update is the whole pose, and a camera that turns to pan legitimately sees the
    frames far from the gauge frame in perspective, at more than the area bound of
    :func:`plausible` (a 50-degree tripod pan: 13x between its ends); a degenerate
    keyframe disagrees with its neighbours as well.

    Returns:
        ``(keyframes, rejected)``: (G, 3, 3) float64 and the number replaced.

    Raises:
        StageError: if no keyframe update is plausible.
    """
    updates = np.linalg.inv(current) @ solved
    good = plausible(updates, width, height)
    if not good.all():
        good |= agrees_with_neighbours(updates, width, height)
    if not good.any():
        raise StageError("locator", "pose graph", "every keyframe update is implausible")
    return bridge(current, solved, good), int((~good).sum())


def agrees_with_neighbours(homographies: NDArray[np.float64], width: int, height: int) -> NDArray[np.bool_]:
    """Flag homographies that :func:`plausible` accepts relative to a neighbour in the sequence.

    Element g passes when ``inv(H[g - 1]) @ H[g]`` or ``inv(H[g]) @ H[g + 1]`` is
    plausible (a sequence of one passes nothing): it folds or rescales nothing relative to
    a neighbour, wherever the sequence as a whole has turned. An isolated wild element
    fails both of its links; its neighbours keep their other one.

    Args:
        homographies: (G, 3, 3) float64, in sequence (consecutive keyframes or frames).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (G,) bool.
    """
    h = np.asarray(homographies, np.float64)
    if len(h) < 2:
        return np.zeros(len(h), bool)
    links = plausible(np.linalg.inv(h[:-1]) @ h[1:], width, height)  # link g: between g and g + 1
    return np.concatenate([[False], links]) | np.concatenate([links, [False]])
