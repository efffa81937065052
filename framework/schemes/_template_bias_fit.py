"""The maximum a-posteriori fit of the template's smooth error (step 4 of :mod:`photonpano.schemes.template_bias`).

Pure numerics on the registrations' linear model: the knot parameters and the prior the
marginal likelihood chooses, one standard deviation for all 8 homography parameters or
one per parameter (automatic relevance determination). Not a plugin.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["PRIOR_GRID_PX", "RELEVANCE_ITERATIONS", "corner_scale", "fit_error", "relevance"]

PRIOR_GRID_PX = np.geomspace(0.005, 2.0, 40)
"""Prior standard deviations of a knot parameter tried by the marginal likelihood, in pixels at the frame corner."""
RELEVANCE_ITERATIONS = 30
"""Updates of the per-parameter priors (:func:`relevance`; 0.34 s for 64 knots on one BLAS thread)."""


def corner_scale(width: int, height: int) -> NDArray[np.float64]:
    """(8,) pixels a unit of each of ``p1..p8`` (about the frame centre) moves a frame corner, roughly."""
    half_w, half_h = width / 2, height / 2
    return np.array([half_w, half_w, half_h, half_h, 1.0, 1.0, half_w * half_w, half_w * half_h])


def fit_error(model: NDArray[np.float64], measured: NDArray[np.float64], information: NDArray[np.float64],
               n_knots: int, width: int, height: int,
               per_parameter: bool = False) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The MAP knot parameters ``a`` of ``measured ~ model @ a`` (see the module, step 4).

    Parameters are scaled to pixels at the frame corner; each registration is weighted by
    its information, whose scale (the noise of the registrations) is the median chi-square
    per parameter of a lightly regularised first fit. The prior is Gaussian: one standard
    deviation for all 8 parameters of every knot, the one that maximises the marginal
    likelihood over :data:`PRIOR_GRID_PX`, or, with ``per_parameter``, then each homography
    parameter's own, shared by its knots (:func:`relevance`).

    Args:
        model: (G, P, K * 8) float64 registrations per unit knot parameter (P = 8, or 6
            for affine registrations: ``p1..p6``).
        measured: (G, P) float64 registered parameters.
        information: (G, P, P) float64 their information.
        n_knots: K.
        width: frame width in pixels.
        height: frame height in pixels.
        per_parameter: a prior per homography parameter.

    Returns:
        ``(a, prior_px)``: (K * 8,) float64 knot parameters and (8,) float64 the prior
        standard deviation of each of p1..p8, in pixels at the frame corner.
    """
    per_knot = np.tile(corner_scale(width, height), n_knots)
    corner = corner_scale(width, height)[:measured.shape[1]]  # the registered parameters
    scaled = model * corner[None, :, None] / per_knot[None, None, :]
    values = measured * corner
    weights = information / (corner[:, None] * corner[None, :])
    weighted = weights @ scaled  # (G, 8, K * 8)
    normal = scaled.reshape(-1, scaled.shape[-1]).T @ weighted.reshape(-1, scaled.shape[-1])
    right = np.einsum("gia,gi->a", weighted, values)
    ridge = 1e-3 * np.trace(normal) / len(normal)
    first = np.linalg.solve(normal + ridge * np.eye(len(normal)), right)
    residual = values - scaled @ first
    noise = max(float(np.median(np.einsum("gi,gij,gj->g", residual, weights, residual))) / len(corner), 1e-300)
    precision, projected_right = normal / noise, right / noise
    eigenvalues, vectors = np.linalg.eigh(precision)
    eigenvalues = np.maximum(eigenvalues, 0.0)
    projected = vectors.T @ projected_right
    evidence = [0.5 * np.sum(projected ** 2 / (eigenvalues + 1 / s ** 2)) - 0.5 * np.sum(np.log1p(s ** 2 * eigenvalues))
                for s in PRIOR_GRID_PX]
    shared = float(PRIOR_GRID_PX[int(np.argmax(evidence))])
    if not per_parameter:
        return vectors @ (projected / (eigenvalues + 1 / shared ** 2)) / per_knot, np.full(8, shared)
    priors = relevance(precision, projected_right, n_knots, shared)
    fitted = np.linalg.solve(precision + np.diag(np.tile(priors ** -2.0, n_knots)), projected_right)
    return fitted / per_knot, priors


def relevance(precision: NDArray[np.float64], right: NDArray[np.float64], n_knots: int, start: float,
               iterations: int = RELEVANCE_ITERATIONS) -> NDArray[np.float64]:
    """Each homography parameter's prior standard deviation, by maximising the marginal likelihood.

    Automatic relevance determination (MacKay, "Bayesian methods for backpropagation
    networks", 1994; Tipping, "Sparse Bayesian learning and the relevance vector machine",
    JMLR 1, 2001): with the posterior covariance ``C`` and mean ``mu`` under the current
    priors, parameter i's prior variance becomes ``sum mu^2 / gamma_i`` over its knots,
    ``gamma_i = sum (1 - C_aa / s_i^2)`` the number of its knot values the registrations
    determine, a fixed number of times. The error level 1 leaves is mostly in one or two
    parameters (a turning camera's keystone ``p7``): one prior for all 8, set by the
    many that are near zero, corrected 0.42 of a keystone ramp injected into the truth
    in one level, one per parameter 0.82 (``benchmarks/convergence.py``).

    Args:
        precision: (K * 8, K * 8) float64 the registrations' information on the knot
            parameters (pixels at the frame corner, knot-major).
        right: (K * 8,) float64 the information-weighted registrations.
        n_knots: K.
        start: the shared prior standard deviation to start from, pixels.
        iterations: updates.

    Returns:
        (8,) float64 prior standard deviations, within :data:`PRIOR_GRID_PX`'s range.
    """
    from scipy.linalg import cho_factor, cho_solve, solve_triangular

    lo, hi = float(PRIOR_GRID_PX[0]) ** 2, float(PRIOR_GRID_PX[-1]) ** 2
    variances = np.full(8, start ** 2)
    identity = np.eye(len(right))
    for _ in range(iterations):
        # the posterior mean, and the diagonal of the posterior covariance from the inverse Cholesky factor
        factor = cho_factor(precision + np.diag(np.tile(1 / variances, n_knots)), lower=True)
        mean = cho_solve(factor, right).reshape(n_knots, 8)
        inverse_factor = solve_triangular(factor[0], identity, lower=True, check_finite=False)
        spread = (inverse_factor ** 2).sum(axis=0).reshape(n_knots, 8).sum(axis=0)
        determined = np.maximum(n_knots - spread / variances, 1e-6)
        variances = np.clip((mean ** 2).sum(axis=0) / determined, lo, hi)
    return np.sqrt(variances)
