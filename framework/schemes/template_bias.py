"""The mosaic template's own error, taken out of the registrations against it.

A mosaic level registers each merged frame against the panorama of the current estimate
(:mod:`photonpano.schemes.mosaic`). That template is made of every binary frame placed
with the estimate's error, so at each canvas point it shows the scene displaced by the
frame-weighted mean error of the frames that see the point; a registration against it
measures a group's error *relative to that mean*, not its error. Errors that the frames
seeing the same canvas share (a slow drift of the pose, a shape error common to a stretch
of the capture) are then measured only in part, and each level removes only that part:
on the evaluation suite the third level's RMSE was still 0.74-0.81 of the second's on
the slowest captures, and registering the same merged frames against a template made
with the *true* motion took the sunset at flux 0.05 from 0.30 px to 0.08 px in one level.
This is the template drift of tracking by template update (Matthews, Ishikawa and Baker,
"The template update problem", PAMI 26, 2004) in the frame-to-mosaic alignment of
Szeliski ("Image alignment and stitching", 2006, Sec. 6.2).

The bias is linear in the error for sub-pixel errors, so it is modelled and removed
(:func:`correct_template_bias`):

1. The estimate's error is modelled as smooth in time: ``e(t) = sum_k psi_k(t) a_k``,
   linear interpolation between ``K`` knots spread over the capture (``a_k``: the 8
   homography parameters about the frame centre, frame side, see
   :mod:`photonpano.information`).
2. The template's displacement at each canvas cell is the frame-weighted mean of the
   displacements ``A_t(x) J(x) e(t)`` of the frames seeing it (``A_t`` the Jacobian of
   frame ``t``'s homography at its pixel ``x``): ``d(X) = L(X) a``, from a sample of the
   frames (:func:`template_displacement`).
3. A registration by least squares on image differences (ECC, Lucas-Kanade) projects the
   displacement field it sees onto the 8 parameters with the template's structure tensor
   ``S``: ``P_g[u] = inv(sum J' S J) sum J' S u`` (the Gauss-Newton step; Baker and
   Matthews, IJCV 56, 2004). Group ``g`` sees its mean error ``e_g`` against the
   template's, so its registration measures ``m_g = -e_g + P_g[L a] + noise``. At an
   affine level (``mosaic.perspective_levels``) both terms are projected onto ``p1..p6``
   the same way (the registration's own error too), and the correction stays affine.
4. ``a`` is the maximum a-posteriori fit of the registrations (weighted by each one's
   information; a Gaussian prior of one standard deviation per knot parameter, in pixels
   at the frame corner, chosen by maximising the marginal likelihood: MacKay, "Bayesian
   interpolation", Neural Computation 4, 1992; with ``mosaic.template_bias_priors:
   per-parameter`` one per homography parameter, his automatic relevance determination:
   :mod:`photonpano.schemes._template_bias_fit`), and each registration is corrected by
   its bias: ``m_g - P_g[L a]``.

Measured on the evaluation suite (48 captures, 2026-11-25, default settings): trajectory
RMSE geometric mean -10 %, 14 captures better by more than 15 % (the bundled office 0.124
-> 0.068 px, the clock 0.441 -> 0.238, coffee 0.052 -> 0.032, Hubble 0.047 -> 0.035, the
dark outdoor scene 0.430 -> 0.194), 3 worse (the room under a 120 Hz lamp over half of it
0.054 -> 0.070, the astronaut 0.016 -> 0.023 and its zigzag at flux 0.05 0.078 -> 0.103);
the base captures at flux 0.05: the sunset 0.224 -> 0.146, coffee 0.200 -> 0.157, the
astronaut 0.127 -> 0.080, dandelions 0.153 -> 0.100, chelsea 0.079 -> 0.081.

Two guards, each chosen on the suite. The short anchor groups at the capture's ends
(``midpoint``'s ``anchor_ends``) are corrected but not fitted: under a lamp flickering
over half the field they span half a period and are biased by it (the facade at 120 Hz:
0.061 px without the correction, 0.092 with them in the fit, 0.063 without). And a
correction larger than the registrations' own moves (root mean square over the level, in
pixels at the frame corner) is scaled down to that size: the template's share of an error
cannot exceed the error, and a larger fit is a mode of the error the registrations hardly
see (the Hubble field's first mosaic level moved its frames by 3.9 px, 0.063 -> 0.189 px).
The knots are one per 4 groups, so that the model follows what level 1 left (a 45 Hz
vibration aliased into 40 knots over 100 000 frames: 0.037 -> 0.059 px); levels of more
than 256 groups (100 000-frame captures, fast pans) are not corrected, where the fit
would cost seconds and the suite showed no gain. Fitting only the error modes the
registrations see well (a truncated generalised eigenbasis) kept the losses away but lost
most of the gains, and so did summing the bias as further virtual levels (a truncated
Neumann series).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import geometry
from ._template_bias_fit import corner_scale, fit_error

__all__ = ["TemplateBias", "correct_template_bias", "template_displacement", "structure_tensors", "knot_weights"]

MAX_KNOTS = 64
"""Most knots of the error model (one per 4 groups; levels of more groups are left as they are)."""
MAX_SAMPLED_FRAMES = 400
"""Most binary frames sampled for the template's displacement (evenly spread; errors are smooth in time)."""


@dataclass(frozen=True)
class TemplateBias:
    """What :func:`correct_template_bias` did (``run.json``'s ``levels[k].template_bias``).

    Attributes:
        knots: knots of the smooth error model (0: the correction was skipped).
        prior_px: the prior standard deviation of each of p1..p8 that the marginal
            likelihood chose, in pixels at the frame corner (empty: skipped).
        correction_px: root mean square over the corrected registrations of the mean
            distance the correction moves a frame's corners, in pixels.
    """

    knots: int
    prior_px: tuple[float, ...]
    correction_px: float

    def record(self) -> dict[str, Any]:
        """The JSON-ready record."""
        return {"knots": self.knots, "prior_px": [round(p, 4) for p in self.prior_px],
                "correction_px": round(self.correction_px, 4)}


def knot_weights(frames: NDArray[np.float64], knots: NDArray[np.float64]) -> NDArray[np.float64]:
    """Linear interpolation weights of frames on knots.

    Args:
        frames: (F,) float64 frame indices.
        knots: (K,) float64 increasing knot positions in frames, K >= 2.

    Returns:
        (F, K) float64 weights (each row sums to 1; frames outside the knots take the
        nearest end).
    """
    index, fraction = _knot_bracket(frames, knots)
    weights = np.zeros((len(frames), len(knots)))
    rows = np.arange(len(frames))
    weights[rows, index] = 1 - fraction
    weights[rows, index + 1] += fraction
    return weights


def _knot_bracket(frames: NDArray[np.floating] | NDArray[np.integer],
                  knots: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """(F,) int64 index of the knot before each frame (at most K - 2), (F,) float64 the way to the next (0-1)."""
    index = np.clip(np.searchsorted(knots, frames, side="right") - 1, 0, len(knots) - 2)
    return index.astype(np.int64), np.clip((frames - knots[index]) / (knots[index + 1] - knots[index]), 0.0, 1.0)


def _cell_centres(shape: tuple[int, int], cell: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(N,) x and (N,) y of the centres of ``cell`` x ``cell`` canvas cells, row-major, covering ``shape``."""
    rows, cols = -(-shape[0] // cell), -(-shape[1] // cell)
    ys, xs = np.mgrid[0:rows, 0:cols]
    return ((xs.ravel() + 0.5) * cell - 0.5).astype(np.float64), ((ys.ravel() + 0.5) * cell - 0.5).astype(np.float64)


def structure_tensors(image: NDArray[np.floating], cell: int) -> NDArray[np.float64]:
    """The structure tensor of an image summed over ``cell`` x ``cell`` cells.

    Args:
        image: (Hc, Wc) float canvas image on a scale where its noise is about the same
            everywhere (NaN where unobserved).
        cell: cell size in pixels.

    Returns:
        (N, 2, 2) float64 ``sum [gx gx, gx gy; gx gy, gy gy]`` per cell (row-major cells
        as :func:`_cell_centres`), over pixels whose 3 x 3 neighbourhood is observed,
        after a Gaussian of 1 px (the locators' pre-filter).
    """
    import cv2

    valid = np.isfinite(image)
    weight = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), 1.0)
    smooth = cv2.GaussianBlur(np.where(valid, image, 0).astype(np.float32), (0, 0), 1.0) / np.maximum(weight, 1e-6)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=1) * 0.5
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=1) * 0.5
    inside = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
    gx, gy = np.where(inside, gx, 0).astype(np.float64), np.where(inside, gy, 0).astype(np.float64)
    h, w = image.shape
    rows, cols = -(-h // cell), -(-w // cell)

    def cell_sum(values: NDArray[np.float64]) -> NDArray[np.float64]:
        padded = np.zeros((rows * cell, cols * cell))
        padded[:h, :w] = values
        return padded.reshape(rows, cell, cols, cell).sum(axis=(1, 3)).ravel()

    xy = cell_sum(gx * gy)
    return np.stack([cell_sum(gx * gx), xy, xy, cell_sum(gy * gy)], axis=-1).reshape(-1, 2, 2)


def template_displacement(homographies: NDArray[np.float64], x_canvas: NDArray[np.float64],
                          y_canvas: NDArray[np.float64], knots: NDArray[np.float64], width: int, height: int,
                          max_frames: int = MAX_SAMPLED_FRAMES) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The template's displacement at canvas points per knot parameter of the estimate's error.

    ``d(X) = sum_t n_t(X) A_t(x) J(x - c) e(t) / sum_t n_t(X)`` with ``e(t) = sum_k psi_k(t)
    a_k`` (:func:`knot_weights`), ``n_t(X)`` 1 where frame ``t`` sees ``X``: the frame-weighted
    mean displacement a template composited from every frame shows (the flux MLE of summed
    detections is, to first order, their frame-weighted mean).

    Args:
        homographies: (T, 3, 3) float64 frame-to-canvas homographies of every frame.
        x_canvas: (N,) float64 canvas x of the points.
        y_canvas: (N,) float64 canvas y of the points.
        knots: (K,) float64 knot positions in frames.
        width: frame width in pixels.
        height: frame height in pixels.
        max_frames: frames sampled (evenly spread over the capture).

    Returns:
        ``(L, frames)``: (N * 2, K * 8) float64 with ``d = L @ a`` (``d`` the points'
        ``(dx, dy)`` pairs flattened, ``a`` the knots' 8 parameters flattened), and (N,)
        float64 the sampled frames seeing each point (0: unobserved, zero rows).
    """
    from ._template_bias_compiled import accumulate_displacement

    n, k = len(homographies), len(knots)
    sampled = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(np.int64))
    lower, fraction = _knot_bracket(sampled, knots)
    frame_h = np.ascontiguousarray(homographies[sampled], np.float64)
    total, frames = accumulate_displacement(frame_h, geometry.invert(frame_h), lower, 1 - fraction,
                                            x_canvas, y_canvas, width, height, k)
    total /= np.maximum(frames, 1)[None, :, None, None]
    return total.transpose(1, 2, 0, 3).reshape(len(x_canvas) * 2, k * 8), frames


def correct_template_bias(homographies: NDArray[np.float64], image: NDArray[np.floating], starts: NDArray[np.int64],
                          stops: NDArray[np.int64], references: NDArray[np.int64],
                          registrations: NDArray[np.float64], ok: NDArray[np.bool_], width: int,
                          height: int, per_parameter_priors: bool = False,
                          affine: bool = False) -> tuple[NDArray[np.float64], TemplateBias]:
    """Registrations against a template of the current estimate, corrected for the template's own error.

    See the module for the model. Args are in the pixels the registrations were made in
    (binned, where the scheme runs binned).

    Args:
        homographies: (T, 3, 3) float64 frame-to-canvas homographies the template was
            composited with (:attr:`~photonpano.records.Panorama.homographies`).
        image: (Hc, Wc) float template on a scale where its noise is about the same
            everywhere (what the locator registered against; NaN unobserved).
        starts: (G,) int64 first frame of each group.
        stops: (G,) int64 frame after each group's last.
        references: (G,) int64 reference frame of each group.
        registrations: (G, 3, 3) float64 merged-frame-to-view homographies (the view: the
            template resampled at the reference frame's pose).
        ok: (G,) bool registrations that succeeded.
        width: frame width in pixels.
        height: frame height in pixels.
        per_parameter_priors: the error model's prior has one standard deviation per
            homography parameter (:func:`~photonpano.schemes._template_bias_fit.relevance`);
            False: one for all 8.
        affine: the registrations are affine (``p7 = p8 = 0``; ``mosaic.perspective_levels``):
            each measures the least-squares projection of the displacement it sees onto
            ``p1..p6``, and its correction stays affine.

    Returns:
        ``(corrected, record)``: (G, 3, 3) float64 registrations (unchanged where ``ok`` is
        False, or the registration's information is singular) and what was done. With
        fewer than 16 or more than ``4 * MAX_KNOTS`` groups, or fewer than 8 usable
        registrations, nothing is corrected (``record.knots`` 0).
    """
    from threadpoolctl import threadpool_limits

    # one BLAS thread: the products' rounding must not depend on the executor (a Dask worker runs with one)
    with threadpool_limits(limits=1, user_api="blas"):
        return _correct(homographies, image, starts, stops, references, registrations, ok, width, height,
                        per_parameter_priors, 6 if affine else 8)


def _correct(homographies: NDArray[np.float64], image: NDArray[np.floating], starts: NDArray[np.int64],
             stops: NDArray[np.int64], references: NDArray[np.int64], registrations: NDArray[np.float64],
             ok: NDArray[np.bool_], width: int, height: int, per_parameter_priors: bool,
             measured_parameters: int) -> tuple[NDArray[np.float64], TemplateBias]:
    """:func:`correct_template_bias`'s work; the registrations measure ``p1..p{measured_parameters}``."""
    g = len(references)
    measured = geometry.params_from_homographies(geometry.about_centre(registrations, width, height))  # (G, 8)
    unchanged = np.asarray(registrations, np.float64).copy(), TemplateBias(0, (), 0.0)
    if int(np.count_nonzero(ok)) < 8:
        return unchanged
    n_knots = g // 4
    if not 4 <= n_knots <= MAX_KNOTS:
        return unchanged
    knots = np.linspace(0, len(homographies) - 1, n_knots)
    cell = max(4, int(round(min(width, height) / 16)))
    x_canvas, y_canvas = _cell_centres(image.shape, cell)
    tensors = structure_tensors(image, cell)  # (N, 2, 2)
    displacement, frames = template_displacement(homographies, x_canvas, y_canvas, knots, width, height)
    observed = frames > 0
    cells = (x_canvas, y_canvas, tensors, observed, width, height)
    references_h = np.ascontiguousarray(homographies[references], np.float64)
    corner = corner_scale(width, height)

    q = slice(0, measured_parameters)

    def conditioned(information: NDArray[np.float64]) -> NDArray[np.bool_]:
        return np.asarray(np.linalg.cond(information / (corner[q, None] * corner[None, q])) < 1e10)

    lengths = stops - starts
    fit = np.flatnonzero(ok & (lengths >= np.median(lengths)))  # not the short anchor groups at the ends
    information, response = _projections(references_h[fit], *cells, displacement=displacement)  # (F, 8, K * 8)
    keep = conditioned(information[:, q, q])
    if int(np.count_nonzero(keep)) < 8:
        return unchanged
    fit, information, response = fit[keep], information[keep], response[keep]
    # a group's mean of the knots' weights: the weights at its middle frame (they are linear between knots)
    middle = (starts[fit] + stops[fit] - 1) / 2
    own = np.einsum("gk,ij->gikj", knot_weights(middle.astype(np.float64), knots), np.eye(8)).reshape(
        len(fit), 8, n_knots * 8)
    # the registration measures its own error and the template's, each projected on its parameters
    information_q = information[:, q, q]
    model = np.linalg.solve(information_q, response[:, q] - information[:, q] @ own)
    errors, prior = fit_error(model, measured[fit][:, q], information_q, n_knots, width, height,
                              per_parameter_priors)
    # every registration's bias: its response to the template's fitted displacement field
    information, response = _projections(references_h, *cells, field=(displacement @ errors).reshape(-1, 2))
    information, response = information[:, q, q], response[:, q]
    usable = ok & conditioned(information)
    if not usable.any():
        return unchanged
    bias = np.zeros((g, 8))
    bias[usable, q] = np.linalg.solve(information[usable], response[usable][..., None])[..., 0]
    size, measured_size = (float(np.sqrt(np.mean((v[usable] * corner) ** 2))) for v in (bias, measured))
    if size > measured_size:  # a share larger than what the registrations moved: scaled down to it
        bias *= measured_size / size
    corrected = geometry.normalize(geometry.from_centre(geometry.homographies_from_params(measured - bias), width,
                                                        height))
    corrected[~usable] = unchanged[0][~usable]
    moved = geometry.mean_corner_distance(corrected[usable], registrations[usable], width, height)
    return corrected, TemplateBias(n_knots, tuple(float(p) for p in prior), float(np.sqrt(np.mean(moved ** 2))))


def _projections(references: NDArray[np.float64], x_canvas: NDArray[np.float64], y_canvas: NDArray[np.float64],
                 tensors: NDArray[np.float64], observed: NDArray[np.bool_], width: int, height: int, *,
                 field: NDArray[np.float64] | None = None, displacement: NDArray[np.float64] | None = None,
                 chunk: int = 64) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each registration's Gauss-Newton information and its response to displacements of the template.

    Args:
        references: (G, 3, 3) reference-frame-to-canvas homographies.
        x_canvas: (N,) canvas x of the cells.
        y_canvas: (N,) canvas y of the cells.
        tensors: (N, 2, 2) structure tensors of the cells.
        observed: (N,) cells the template observes.
        width: frame width in pixels.
        height: frame height in pixels.
        field: (N, 2) one displacement field of the template, or None.
        displacement: (N * 2, Q) displacement fields (the cells' ``(dx, dy)`` flattened), e.g.
            per knot parameter (:func:`template_displacement`), or None.
        chunk: groups per batch with ``displacement`` (memory: chunk x 8 x N x 2 float64).

    Returns:
        ``(information, response)``: (G, 8, 8) ``sum D' S D`` over the observed cells each
        reference frame sees, and the response ``sum D' S d``: (G, 8) to ``field``, or
        (G, 8, Q) to ``displacement`` (``D``: the canvas displacement per unit of the
        frame's parameters).
    """
    from ._template_bias_compiled import gauss_newton_terms

    g, points = len(references), len(x_canvas)
    inverses = geometry.invert(references)
    if displacement is None:
        zero = np.zeros((points, 2)) if field is None else np.ascontiguousarray(field, np.float64)
        information, response, _ = gauss_newton_terms(references, inverses, x_canvas, y_canvas, tensors, observed,
                                                      zero, width, height, False)
        return information, response
    information = np.empty((g, 8, 8))
    responses = np.empty((g, 8, displacement.shape[1]))
    for start in range(0, g, chunk):
        part = slice(start, start + chunk)
        information[part], _, weighted = gauss_newton_terms(references[part], inverses[part], x_canvas, y_canvas,
                                                            tensors, observed, np.zeros((points, 2)), width,
                                                            height, True)
        responses[part] = (weighted.reshape(-1, points * 2) @ displacement).reshape(len(weighted), 8, -1)
    return information, responses
