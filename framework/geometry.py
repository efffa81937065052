"""Homography helpers shared by every stage.

Conventions (see ``docs/conventions.md``): a homography acts on homogeneous pixel
coordinates ``(x, y, 1)`` with x to the right, y down and pixel centres at integer
coordinates (the OpenCV convention). Homography stacks are ``(N, 3, 3)`` float64 and are
kept normalised so that ``H[2, 2] == 1``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "normalize",
    "invert",
    "params_from_homographies",
    "homographies_from_params",
    "about_centre",
    "from_centre",
    "corners",
    "pixel_grid",
    "apply",
    "scale_matrix",
    "translation",
    "extents_apart",
    "footprint_bounds",
]


def normalize(homographies: NDArray[np.float64]) -> NDArray[np.float64]:
    """Scale homographies so that their bottom-right entry is 1.

    Args:
        homographies: (..., 3, 3) float array.

    Returns:
        (..., 3, 3) float64 array, a new array.

    Raises:
        ValueError: if a bottom-right entry is zero (a degenerate homography).
    """
    h = np.asarray(homographies, dtype=np.float64)
    scale = h[..., 2:3, 2:3]
    if (scale == 0).any():  # the method: np.any's Python wrapper costs more than the test (called per sub-batch)
        raise ValueError("degenerate homography: H[2, 2] == 0")
    return h / scale


def invert(homographies: NDArray[np.float64]) -> NDArray[np.float64]:
    """Invert homographies in closed form (the adjugate over the determinant).

    For stacks of many homographies (one per binary frame) this is 7 times faster than
    ``np.linalg.inv``, which factorises each 3x3 matrix on its own (100 000: 6 vs 43 ms);
    the two agree to rounding (5e-16 relative) for the homographies of a capture.

    Args:
        homographies: (..., 3, 3) float array, invertible.

    Returns:
        (..., 3, 3) float64 inverses (not normalised); inf or NaN where a determinant is 0.
    """
    h = np.asarray(homographies, dtype=np.float64)
    a, b, c, d, e, f, g, k, m = h.reshape(-1, 9).T.copy()  # one contiguous row per entry
    adjugate = np.empty((9, len(a)))
    adjugate[0], adjugate[1], adjugate[2] = e * m - f * k, c * k - b * m, b * f - c * e
    adjugate[3], adjugate[4], adjugate[5] = f * g - d * m, a * m - c * g, c * d - a * f
    adjugate[6], adjugate[7], adjugate[8] = d * k - e * g, b * g - a * k, a * e - b * d
    det = a * adjugate[0] + b * adjugate[3] + c * adjugate[6]
    with np.errstate(divide="ignore", invalid="ignore"):
        adjugate /= det
    return adjugate.T.reshape(h.shape)


def params_from_homographies(homographies: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return the 8 Lucas-Kanade parameters p1..p8 of each homography.

    ``H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]`` (paper Eq. 4; Baker and
    Matthews, "Lucas-Kanade 20 years on", 2004).

    Args:
        homographies: (N, 3, 3) float array.

    Returns:
        (N, 8) float64 array of ``p1..p8``.
    """
    h = normalize(homographies)
    return np.stack(
        [h[..., 0, 0] - 1, h[..., 1, 0], h[..., 0, 1], h[..., 1, 1] - 1,
         h[..., 0, 2], h[..., 1, 2], h[..., 2, 0], h[..., 2, 1]],
        axis=-1,
    )


def homographies_from_params(params: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of :func:`params_from_homographies`.

    Args:
        params: (N, 8) float array of ``p1..p8``.

    Returns:
        (N, 3, 3) float64 homographies.
    """
    p = np.asarray(params, dtype=np.float64)
    h = np.empty(p.shape[:-1] + (3, 3))
    h[..., 0, 0] = 1 + p[..., 0]
    h[..., 1, 0] = p[..., 1]
    h[..., 0, 1] = p[..., 2]
    h[..., 1, 1] = 1 + p[..., 3]
    h[..., 0, 2] = p[..., 4]
    h[..., 1, 2] = p[..., 5]
    h[..., 2, 0] = p[..., 6]
    h[..., 2, 1] = p[..., 7]
    h[..., 2, 2] = 1
    return h


def corners(width: int, height: int, *, edges: bool = False) -> NDArray[np.float64]:
    """Return the four corners of a ``width`` x ``height`` frame.

    Args:
        width: frame width in pixels.
        height: frame height in pixels.
        edges: if False (default) the centres of the four corner pixels, e.g. ``(0, 0)``
            and ``(width - 1, height - 1)``; if True the outer edges of the frame
            (``-0.5`` and ``width - 0.5``), which bound its footprint.

    Returns:
        (4, 2) float64 ``(x, y)`` in pixels, clockwise from the top-left.
    """
    lo, hx, hy = (-0.5, width - 0.5, height - 0.5) if edges else (0.0, width - 1.0, height - 1.0)
    return np.array([[lo, lo], [hx, lo], [hx, hy], [lo, hy]], dtype=np.float64)


def pixel_grid(width: int, height: int, per_axis: int) -> NDArray[np.float64]:
    """Return ``per_axis`` x ``per_axis`` pixel centres spread evenly over a frame, corners included.

    Args:
        width: frame width in pixels.
        height: frame height in pixels.
        per_axis: points per axis (>= 1).

    Returns:
        (per_axis ** 2, 2) float64 ``(x, y)`` whole pixel centres (the even spread rounded),
        row by row from the top-left.
    """
    xs, ys = np.meshgrid(np.round(np.linspace(0, width - 1, per_axis)), np.round(np.linspace(0, height - 1, per_axis)))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def apply(homographies: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Map points through each homography.

    Args:
        homographies: (N, 3, 3) or (3, 3) float array.
        points: (K, 2) float array of ``(x, y)`` pixel coordinates, shared by all
            homographies, or (N, K, 2) with one set of points per homography.

    Returns:
        (N, K, 2) float64 (or (K, 2) for a single homography) mapped coordinates.
    """
    h = np.asarray(homographies, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    hom = np.concatenate([pts, np.ones(pts.shape[:-1] + (1,))], axis=-1)  # (..., K, 3)
    out = hom @ np.swapaxes(h, -1, -2)  # (..., K, 3)
    return out[..., :2] / out[..., 2:3]


def mean_corner_distance(a: NDArray[np.float64], b: NDArray[np.float64], width: int,
                         height: int) -> NDArray[np.float64]:
    """Mean distance of a frame's four corners mapped by ``a`` and by ``b``.

    The per-frame error measure of :func:`~photonpano.metrics.trajectory_error`.

    Args:
        a: (N, 3, 3) float64 homographies (or (1, 3, 3), broadcast).
        b: (N, 3, 3) float64 homographies (or (1, 3, 3), broadcast).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (N,) float64 distances in the pixels of the homographies' target.
    """
    c = corners(width, height)
    return np.linalg.norm(apply(a, c) - apply(b, c), axis=-1).mean(axis=-1)


def scale_matrix(scale: float) -> NDArray[np.float64]:
    """Return the homography that maps pixel coordinates to a grid ``scale`` times finer.

    With pixel centres at integers, pixel ``i`` covers ``[i - 0.5, i + 0.5]``, so the
    map is ``x' = scale * (x + 0.5) - 0.5``.

    Args:
        scale: super-resolution scale (> 0), e.g. 2.0.

    Returns:
        (3, 3) float64.
    """
    off = 0.5 * (scale - 1.0)
    return np.array([[scale, 0, off], [0, scale, off], [0, 0, 1.0]])


def translation(dx: float, dy: float) -> NDArray[np.float64]:
    """Return the (3, 3) float64 homography translating by ``(dx, dy)`` pixels."""
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


def about_centre(homographies: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    """Return ``inv(T_c) @ H @ T_c``: the homographies with the frame centre as origin.

    ``T_c`` translates by the frame centre ``((width - 1) / 2, (height - 1) / 2)`` (pixel
    centres at integer coordinates). About the centre, ``p5, p6`` of
    :func:`params_from_homographies` are the frame centre's displacement in pixels and
    ``p1..p4`` the frame's rotation, scale and shear wherever it is (the parameters the
    levels interpolate and the registrations' information is given in).

    Args:
        homographies: (..., 3, 3) float array mapping pixel coordinates to pixel coordinates.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (..., 3, 3) float64, not normalised.
    """
    cx, cy = (width - 1) / 2, (height - 1) / 2
    return translation(-cx, -cy) @ np.asarray(homographies, np.float64) @ translation(cx, cy)


def from_centre(homographies: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    """Inverse of :func:`about_centre`: ``T_c @ H @ inv(T_c)``, back to pixel coordinates.

    Args:
        homographies: (..., 3, 3) float array about the frame centre.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (..., 3, 3) float64, not normalised.
    """
    cx, cy = (width - 1) / 2, (height - 1) / 2
    return translation(cx, cy) @ np.asarray(homographies, np.float64) @ translation(-cx, -cy)


def extents_apart(offset: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    """How far apart two frames' centres are, in frame extents along the offset between them.

    Args:
        offset: (N, 2) float64 displacements ``(dx, dy)`` of frame centres, in pixels.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (N,) float64 each displacement's length over the frame's extent along it
        (``|ux| width + |uy| height`` for the unit direction u): 1 where two frames side by
        side just stop overlapping, 0 for no displacement.
    """
    distance = np.linalg.norm(offset, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = np.abs(offset) / distance[:, None]
    extent = np.where(distance > 0, direction[:, 0] * width + direction[:, 1] * height, 1.0)
    return np.where(distance > 0, distance / extent, 0.0)


def footprint_bounds(
    homographies: NDArray[np.float64], width: int, height: int
) -> tuple[float, float, float, float]:
    """Return the bounding box of the frames' footprints after warping.

    Args:
        homographies: (N, 3, 3) frame-to-target homographies.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``(x_min, y_min, x_max, y_max)`` in target pixel coordinates (outer edges).
    """
    pts = apply(homographies, corners(width, height, edges=True)).reshape(-1, 2)
    return (float(pts[:, 0].min()), float(pts[:, 1].min()),
            float(pts[:, 0].max()), float(pts[:, 1].max()))
