"""The pose graph of a camera turning about its centre: one focal length and a rotation per keyframe.

A camera on a tripod (or held still while it pans) turns about its optical centre, and
two of its frames are then related by ``K R_a^T R_b K^-1`` (Hartley and Zisserman,
*Multiple View Geometry*, 2nd ed., Sec. 8.4.2; Szeliski, *Image Alignment and Stitching*,
2006, Sec. 2.1; OpenCV's stitching module estimates the same model,
``cv::detail::BundleAdjusterRay``). Where the eight-parameter pose graph
(:func:`photonpano.posegraph.refine_keyframes`) gives each keyframe its own keystone and
scale, a chain of pairs that measure the turn's perspective poorly (scenes of little
texture, rescued on binned frames) bends the trajectory by pixels over a wide pan; the
turning camera has three parameters per keyframe and one focal length for the whole
level, so the perspective follows from the turn. :func:`fit_turning_camera` solves it;
:func:`photonpano.schemes.pairwise.locate_keyframes` keeps it for a level that turns where
it agrees with the pairs nearly as well as the free solution.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .posegraph import median_disagreement, pair_weights, robust_least_squares
from .records import PairRegistrations

if TYPE_CHECKING:
    import scipy.sparse

__all__ = ["TurningFit", "fit_turning_camera", "turning_keyframes", "focal_from_keyframes", "FOCAL_SEARCH_PX",
           "TURNING_DISAGREEMENT_RATIO"]

FOCAL_SEARCH_PX = (0.2, 50.0)
"""Focal lengths :func:`focal_from_keyframes` searches, in frame widths (geometric grid)."""


TURNING_DISAGREEMENT_RATIO = 1.5
"""Most a turning camera's median corner disagreement with a level's registered pairs may exceed the
eight-parameter solution's, as a factor, for :func:`turning_keyframes` to keep it. Tripod pans (the
suite's recipe with ``source.pan_model: rotation``, 28 photographs whose level turns): 0.99-1.44
on 25; where the turn's model does not hold the pairs (the horse, a checkerboard and a phantom,
whose level 1 is all rescues): 2.3, 2.9 and 4.2 (docs/accuracy.md, "A camera turning about its centre")."""


@dataclass(frozen=True)
class TurningFit:
    """A level's keyframes as a camera turning about its centre.

    Attributes:
        keyframes: (G, 3, 3) float64 frame-to-panorama homographies, each
            ``initial[0] @ T_c K R_0^T R_g K^-1 T_c^-1`` (``T_c`` the translation to the
            frame centre, ``K = diag(f, f, 1)``, ``R_0`` the first keyframe's rotation,
            the identity).
        focal_px: the focal length ``f`` in frame pixels.
        start_focal_px: the focal length the solve started from (:func:`focal_from_keyframes`).
    """

    keyframes: NDArray[np.float64]
    focal_px: float
    start_focal_px: float


def focal_from_keyframes(centred: NDArray[np.float64], width: int) -> float:
    """The focal length that makes homographies about the frame centre closest to rotations.

    For ``H = K R K^-1`` up to scale, ``K^-1 H K / det^(1/3)`` is a rotation; the focal
    length is searched on a geometric grid (:data:`FOCAL_SEARCH_PX` frame widths, 300
    steps) for the least ``sum ||A^T A - I||^2`` over the keyframes (Szeliski 2006,
    Sec. 4.3, estimates it from pairs in closed form; a search over all keyframes at once
    does not depend on any single pair's perspective).

    Args:
        centred: (G, 3, 3) float64 homographies about the frame centre
            (:func:`photonpano.geometry.about_centre`), each relative to the first keyframe.
        width: frame width in pixels.

    Returns:
        The focal length in frame pixels.
    """
    candidates = np.geomspace(FOCAL_SEARCH_PX[0] * width, FOCAL_SEARCH_PX[1] * width, 300)
    k = np.zeros((len(candidates), 1, 3, 3))
    k[:, 0, 0, 0] = k[:, 0, 1, 1] = candidates
    k[:, 0, 2, 2] = 1
    k_inv = np.linalg.inv(k)
    a = k_inv @ centred[None] @ k  # (F, G, 3, 3)
    a = a / np.cbrt(np.linalg.det(a))[..., None, None]
    error = ((np.swapaxes(a, -1, -2) @ a - np.eye(3)) ** 2).sum(axis=(1, 2, 3))
    return float(candidates[int(np.argmin(error))])


def fit_turning_camera(initial: NDArray[np.float64], pair_index: NDArray[np.int64], pairs: PairRegistrations,
                       width: int, height: int) -> TurningFit:
    """Solve a level's pose graph for a camera turning about its centre.

    The same problem as :func:`photonpano.posegraph.refine_keyframes` (a 3x3 grid of
    frame b's points should map to the same place through the pair's homography and
    through the keyframes, residuals in frame a's pixels weighted by the square root of
    the pair's inliers over their median, soft-L1 loss with a 1 px scale) on fewer
    unknowns: each keyframe g > 0 is a rotation ``R_g`` (a rotation vector) of one
    pinhole camera whose principal point is the frame centre, and the focal length ``f``
    is shared (solved as ``log f``). The first keyframe is held at ``initial[0]``
    (gauge). Rotations start from the initial keyframes (the nearest rotation to
    ``K^-1 H K``, Markley's method in :meth:`scipy.spatial.transform.Rotation.from_matrix`)
    and the focal length from :func:`focal_from_keyframes`; the solve is
    :func:`~photonpano.posegraph.robust_least_squares` on the pairs' sparse Jacobian (forward
    differences, seven per pair whatever the graph's width).

    Args:
        initial: (G, 3, 3) float64 keyframe homographies (frame to panorama), e.g. the
            eight-parameter pose graph's solution; G >= 2.
        pair_index: (P, 2) int64 keyframe indices ``(a, b)`` of each pair.
        pairs: the P pair registrations (homography b to a); failed pairs are ignored.
            The graph must connect every keyframe (bridge failed consecutive pairs).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        The fit (:class:`TurningFit`).

    Raises:
        ValueError: for fewer than two keyframes or no registered pair.
    """
    import scipy.sparse  # here, not at import: most levels do not turn (scipy.spatial and sparse: 0.13 s)
    from scipy.spatial.transform import Rotation

    g = len(initial)
    use = pairs.ok & (pair_index[:, 0] != pair_index[:, 1])
    if g < 2 or not use.any():
        raise ValueError(f"fit_turning_camera: needs two keyframes and a registered pair, got {g} and {int(use.sum())}")
    a, b = pair_index[use, 0], pair_index[use, 1]
    centred = geometry.about_centre(np.linalg.inv(initial[0]) @ initial, width, height)
    centred = centred / centred[:, 2:3, 2:3]
    start_focal = focal_from_keyframes(centred, width)
    k = np.diag([start_focal, start_focal, 1.0])
    rotations = np.linalg.inv(k) @ centred @ k
    rotations /= np.cbrt(np.linalg.det(rotations))[:, None, None]
    vectors = Rotation.from_matrix(rotations).as_rotvec()
    grid = geometry.pixel_grid(width, height, 3) - np.array([(width - 1) / 2, (height - 1) / 2])  # about the centre
    measured = geometry.apply(geometry.about_centre(pairs.homographies[use], width, height), grid)  # (E, 9, 2)
    weight = pair_weights(pairs.inliers[use])

    def keyframe_rotations(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        """(G, 3) rotation vectors (the first zero) and the focal length of unknowns ``x``."""
        return np.concatenate([np.zeros((1, 3)), x[:-1].reshape(g - 1, 3)]), float(np.exp(x[-1]))

    def pair_residuals(vector_a: NDArray[np.float64], vector_b: NDArray[np.float64],
                       focal: float) -> NDArray[np.float64]:
        """(E, 18) weighted ``M x - K R_a^T R_b K^-1 x`` in frame a's pixels, given each pair's two rotations."""
        turn_a, turn_b = Rotation.from_rotvec(vector_a).as_matrix(), Rotation.from_rotvec(vector_b).as_matrix()
        camera, camera_inv = np.diag([focal, focal, 1.0]), np.diag([1 / focal, 1 / focal, 1.0])
        relative = camera @ np.swapaxes(turn_a, 1, 2) @ turn_b @ camera_inv
        return ((measured - geometry.apply(relative, grid)) * weight[:, None, None]).reshape(len(a), 18)

    # Each pair's 18 residuals depend on its two keyframes' rotations and on the focal length:
    # 7 forward differences per pair, all pairs at once, whatever the graph's width.
    rows = np.arange(18 * len(a)).reshape(len(a), 18)
    keyframe_columns = [(node[:, None] - 1) * 3 + np.arange(3) for node in (a, b)]  # (E, 3) each; -3..-1: gauge

    def linearise(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], scipy.sparse.csr_matrix]:
        """(E * 18,) weighted residuals of unknowns ``x`` and their (E * 18, 3 (G - 1) + 1) Jacobian."""
        vectors_g, focal = keyframe_rotations(x)
        ends = (vectors_g[a], vectors_g[b])
        base = pair_residuals(*ends, focal)
        step = 1e-7
        entries, row_index, column_index = [], [], []
        for side, columns in enumerate(keyframe_columns):
            for axis in range(3):
                moved = list(ends)
                moved[side] = moved[side].copy()
                moved[side][:, axis] += step
                free = columns[:, axis] >= 0
                entries.append(((pair_residuals(moved[0], moved[1], focal) - base) / step)[free])
                row_index.append(rows[free])
                column_index.append(np.broadcast_to(columns[free, axis, None], rows[free].shape))
        entries.append((pair_residuals(*ends, focal * np.exp(step)) - base) / step)
        row_index.append(rows)
        column_index.append(np.full(rows.shape, 3 * (g - 1)))
        jacobian = scipy.sparse.csr_matrix((np.concatenate([e.ravel() for e in entries]),
                                            (np.concatenate([r.ravel() for r in row_index]),
                                             np.concatenate([c.ravel() for c in column_index]))),
                                           shape=(rows.size, 3 * (g - 1) + 1))
        return base.ravel(), jacobian

    start = np.concatenate([vectors[1:].ravel(), [np.log(start_focal)]])
    solution = robust_least_squares(linearise, start)
    vectors, focal = keyframe_rotations(solution)
    rot = Rotation.from_rotvec(vectors).as_matrix()
    turned = geometry.from_centre(np.diag([focal, focal, 1.0]) @ rot @ np.diag([1 / focal, 1 / focal, 1.0]),
                                  width, height)
    return TurningFit(geometry.normalize(initial[0] @ turned), focal, start_focal)


def turning_keyframes(solved: NDArray[np.float64], pair_index: NDArray[np.int64], graph: PairRegistrations,
                      trusted: NDArray[np.bool_], width: int, height: int
                      ) -> tuple[NDArray[np.float64], dict[str, float | bool]]:
    """A level's keyframes as a turning camera, where that agrees with its pairs nearly as well as ``solved``.

    The G - 1 consecutive pairs come first in ``graph``; those it does not count
    registered (failed, or rejected as outliers) are bridged by ``solved``'s own steps
    with a token weight of one inlier, as the eight-parameter solve bridges them, so that
    the graph connects every keyframe. The fit (:func:`fit_turning_camera`) is kept where
    the median corner disagreement (:func:`~photonpano.posegraph.median_disagreement`,
    pixels) of its pair maps with the ``trusted`` registrations is at most
    :data:`TURNING_DISAGREEMENT_RATIO` times ``solved``'s.

    Args:
        solved: (G, 3, 3) float64 the eight-parameter pose graph's keyframes.
        pair_index: (P, 2) int64 keyframe indices ``(a, b)``, the G - 1 consecutive pairs first.
        graph: the P registrations the pose graph was solved on (``ok`` as it used them).
        trusted: (P,) bool the registrations measured and not rejected (the disagreement's
            pairs; at least one).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``(keyframes, figures)``: the fit's keyframes where kept, else ``solved``; and
        ``{"kept", "focal_px", "start_focal_px", "disagreement_px", "free_disagreement_px"}``
        (``run.json``'s ``registration_check.turning_camera``).

    Raises:
        ValueError: for fewer than two keyframes (:func:`fit_turning_camera`).
    """
    steps = len(solved) - 1
    bridge = ~graph.ok[:steps]
    homographies, inliers, ok = graph.homographies.copy(), graph.inliers.copy(), graph.ok.copy()
    homographies[:steps][bridge] = (np.linalg.inv(solved[:-1]) @ solved[1:])[bridge]
    inliers[:steps][bridge], ok[:steps] = 1, True
    fit = fit_turning_camera(solved, pair_index, PairRegistrations(homographies, graph.matches, inliers, ok),
                             width, height)

    turned, free = (median_disagreement(k, pair_index, graph, trusted, width, height) for k in (fit.keyframes, solved))
    kept = bool(np.isfinite(turned)) and turned <= TURNING_DISAGREEMENT_RATIO * free
    figures = {"kept": kept, "focal_px": round(fit.focal_px, 2), "start_focal_px": round(fit.start_focal_px, 2),
               "disagreement_px": round(turned, 4), "free_disagreement_px": round(free, 4)}
    return (fit.keyframes if kept else solved), figures
