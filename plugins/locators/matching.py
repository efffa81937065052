"""Robust motion from matched features: the motion models, GRIC model selection, ratio-test matching.

Used by the feature locators (``opencv-sift``, ``opencv-orb``;
:class:`~photonpano.plugins.locators.common.FeatureLocator`): descriptors are matched
with Lowe's ratio test (:func:`ratio_matches`, exact L2 through
:class:`IntegralL2Matcher` where it pays) and a motion model is fitted robustly
(:func:`robust_motion`; ``auto`` picks homography, affine or similarity per pair by
:func:`gric`). Only numpy at module level; OpenCV is imported inside functions. Not a
plugin (it registers nothing).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from .common import PairResult

__all__ = ["MotionModel", "MOTION_PARAMETERS", "INLIERS_PER_PARAMETER", "robust_method", "robust_motion", "gric",
           "ratio_test_motion", "ratio_matches", "IntegralL2Matcher"]


MotionModel = Literal["auto", "homography", "affine", "similarity"]
"""Motion models a feature locator can fit; ``auto`` picks one per pair by :func:`gric`."""

MOTION_PARAMETERS = {"homography": 8, "affine": 6, "similarity": 4}
"""Degrees of freedom of each motion model."""

INLIERS_PER_PARAMETER = 3
"""``motion: auto`` considers an affine model or a homography only where it has at least this
many inliers per degree of freedom (18 and 24); the similarity is always a candidate. GRIC
assumes the inliers are found: with a few dozen tentative matches, mostly wrong, a model with
more parameters also gathers more chance inliers, and a near tie decides it (a dark room at
flux 0.05, level 1: a homography of 17 inliers chosen over a similarity of 12 by 0.9 GRIC
units, its perspective 3.9 px off at the frame corner, which the chain carried into every
later frame: level 1 1.45 px RMSE, 0.32 with this rule; the final trajectory 0.423 -> 0.064
px). Measured on the evaluation suite in docs/accuracy.md: at 5 per degree of freedom
dandelions lost its useful affine pairs, at 2 the room kept its homography."""


def robust_method(name: str) -> int:
    """Return OpenCV's flag for a robust estimator name (``ransac``, ``usac-magsac``, ``usac-accurate``, ``lmeds``)."""
    import cv2

    return {"ransac": cv2.RANSAC, "usac-magsac": cv2.USAC_MAGSAC, "usac-accurate": cv2.USAC_ACCURATE,
            "lmeds": cv2.LMEDS}[name]


def gric(model: NDArray[np.float64], src: NDArray[np.float32], dst: NDArray[np.float32], sigma_px: float,
         parameters: int) -> float:
    """Torr's Geometric Robust Information Criterion of a 2D motion model (lower is better).

    ``GRIC = sum_i min(e_i^2 / sigma^2, 2 (r - d)) + lambda1 d n + lambda2 k`` with data
    dimension r = 4 (two image points), model dimension d = 2 (every model here maps
    points to points), ``lambda1 = ln r``, ``lambda2 = ln(r n)`` and k the model's degrees
    of freedom (Torr, "Bayesian model estimation and selection for epipolar geometry and
    generic manifold fitting", IJCV 50(1), 2002, Eq. 22). The residual term caps outliers,
    the parameter term charges each degree of freedom: a homography wins only where its
    extra parameters explain the data beyond the noise.

    Args:
        model: (3, 3) float64 mapping ``src`` to ``dst``.
        src: (N, 2) float32 points of frame b, pixels.
        dst: (N, 2) float32 matching points of frame a, pixels.
        sigma_px: standard deviation of keypoint positions, pixels.
        parameters: degrees of freedom k of the model.

    Returns:
        The criterion (dimensionless).
    """
    from ._compiled import capped_transfer_error  # compiled: 3 per pair at level 1, on the workers

    n = len(src)
    residual = capped_transfer_error(np.asarray(model, np.float64), src, dst, float(sigma_px) ** 2, 4.0)
    return float(residual + 2 * np.log(4) * n + np.log(4 * n) * parameters)


def robust_motion(src: NDArray[np.float32], dst: NDArray[np.float32], *, motion: str = "homography",
                  method: str = "usac-magsac", threshold_px: float = 1.5, min_inliers: int = 12,
                  refine: bool = True) -> PairResult:
    """Fit a motion model to tentative correspondences with an OpenCV robust estimator.

    Homographies are fitted by ``cv2.findHomography`` (refit to all inliers by least
    squares with ``refine``), affine and similarity models by ``cv2.estimateAffine2D`` and
    ``cv2.estimateAffinePartial2D`` (Levenberg-Marquardt on the inliers with ``refine``).
    With ``motion="auto"`` all three are fitted and, of those with at least
    :data:`INLIERS_PER_PARAMETER` inliers per degree of freedom (the similarity always; all
    of them where none qualifies), the one of lowest :func:`gric` (keypoint noise
    ``threshold_px / 2``) is returned. This guards against degenerate
    configurations: when the static scene's keypoints lie on a thin band (a floor, a
    horizon), a homography can fit them *and* a few keypoints of an independently moving
    object, a lower-order model fitted to the band alone scores better.

    Args:
        src: (N, 2) float32 points of frame b (pixels, photonpano's convention).
        dst: (N, 2) float32 matching points of frame a.
        motion: ``homography``, ``affine``, ``similarity`` or ``auto``.
        method: robust estimator, see :func:`robust_method` (affine and similarity
            models use RANSAC unless ``lmeds``).
        threshold_px: inlier threshold in pixels.
        min_inliers: fewer inliers than this flags the pair as failed.
        refine: refit each model to its inliers.

    Returns:
        The pair's result: (3, 3) float64 homography mapping ``src`` to ``dst`` (of the
        chosen model), the number of correspondences and of the model's inliers.
    """
    import cv2

    fits: dict[str, tuple[NDArray[np.float64], int]] = {}
    for name in (("homography", "affine", "similarity") if motion == "auto" else (motion,)):
        if name == "homography":
            model, mask = cv2.findHomography(src, dst, robust_method(method), threshold_px, maxIters=5000,
                                             confidence=0.999)
            if model is not None and mask is not None and refine and mask.sum() >= 8:
                refined, _ = cv2.findHomography(src[mask.ravel() > 0], dst[mask.ravel() > 0], 0)
                model = refined if refined is not None else model
        else:
            estimate = cv2.estimateAffine2D if name == "affine" else cv2.estimateAffinePartial2D
            affine, mask = estimate(src, dst, method=cv2.LMEDS if method == "lmeds" else cv2.RANSAC,
                                    ransacReprojThreshold=threshold_px, maxIters=5000, confidence=0.999,
                                    refineIters=10 if refine else 0)
            model = None if affine is None else np.vstack([affine, [0.0, 0.0, 1.0]])
        if model is not None and mask is not None and np.all(np.isfinite(model)) and abs(model[2, 2]) > 1e-12:
            fits[name] = (model.astype(np.float64) / model[2, 2], int(mask.sum()))
    if not fits:
        return PairResult(matches=len(src))
    if motion == "auto":
        supported = {name: fit for name, fit in fits.items()
                     if name == "similarity" or fit[1] >= INLIERS_PER_PARAMETER * MOTION_PARAMETERS[name]}
        fits = supported or fits
    chosen = min(fits, key=lambda name: gric(fits[name][0], src, dst, threshold_px / 2, MOTION_PARAMETERS[name]))
    h, n_in = fits[chosen]
    ok = n_in >= min_inliers and abs(np.linalg.det(h[:2, :2])) > 1e-3
    return PairResult(h, len(src), n_in, bool(ok))


def ratio_test_motion(matcher: Any, points_a: NDArray, descriptors_a: NDArray, points_b: NDArray,
                      descriptors_b: NDArray, config: Any) -> PairResult:
    """Match descriptors of frame b to frame a, keep Lowe's ratio-test survivors, fit :func:`robust_motion`.

    Args:
        matcher: an OpenCV ``DescriptorMatcher`` (e.g. ``cv2.BFMatcher``) for the
            descriptors, or an :class:`IntegralL2Matcher` (see :func:`ratio_matches`).
        points_a: (Ka, 2) keypoints of frame a, pixels (photonpano's convention).
        descriptors_a: (Ka, D) their descriptors.
        points_b: (Kb, 2) keypoints of frame b.
        descriptors_b: (Kb, D) their descriptors.
        config: the locator's config, with ``ratio``, ``min_inliers``, ``motion``,
            ``method``, ``reprojection_px`` and ``refine``.

    Returns:
        The pair's result (b to a); failed (``ok=False``) with fewer than four keypoints
        in a frame or fewer than ``max(4, min_inliers)`` ratio-test matches.
    """
    if len(points_a) < 4 or len(points_b) < 4:
        return PairResult()
    query, train = ratio_matches(matcher, descriptors_b, descriptors_a, config.ratio)
    if len(query) < max(4, config.min_inliers):
        return PairResult(matches=len(query))
    src = np.asarray(points_b, np.float32)[query]
    dst = np.asarray(points_a, np.float32)[train]
    return robust_motion(src, dst, motion=config.motion, method=config.method, threshold_px=config.reprojection_px,
                         min_inliers=config.min_inliers, refine=config.refine != "none")


def ratio_matches(matcher: Any, descriptors_query: NDArray, descriptors_train: NDArray,
                  ratio: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Lowe's ratio test: each query descriptor's nearest train descriptor, if clearly the nearest.

    Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004, Sec. 7.1:
    a match is kept when its distance is below ``ratio`` times the second-nearest's.

    Args:
        matcher: an OpenCV ``DescriptorMatcher`` (its ``knnMatch`` with k = 2), or an
            object with this function's signature as a ``ratio_matches`` method
            (:class:`IntegralL2Matcher`).
        descriptors_query: (Kq, D) descriptors of the query frame (frame b of a pair).
        descriptors_train: (Kt, D) descriptors of the train frame (frame a).
        ratio: the threshold, in (0, 1).

    Returns:
        ``(query, train)``: (M,) int64 indices of the kept matches, in query order.
    """
    if hasattr(matcher, "ratio_matches"):
        return matcher.ratio_matches(descriptors_query, descriptors_train, ratio)
    knn = matcher.knnMatch(descriptors_query, descriptors_train, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    return (np.array([m.queryIdx for m in good], np.int64).reshape(-1),
            np.array([m.trainIdx for m in good], np.int64).reshape(-1))


class IntegralL2Matcher:
    """Brute-force L2 matching of integer-valued descriptors (OpenCV SIFT's) as one BLAS product.

    OpenCV's SIFT descriptors are 128 integers in 0..255 stored as float32, so every
    squared distance ``|q|^2 - 2 q.t + |t|^2`` and every partial sum of it is an integer
    below 2**24, exact in float32 whatever order the matrix product sums in: the
    distances, hence the ratio test's decisions, are those of
    ``cv2.BFMatcher(cv2.NORM_L2)`` (a tie for the nearest fails the test either way), at
    about a fifth of its time (300 x 300 SIFT descriptors: 0.32 against 1.7 ms on one
    core). It assumes what :meth:`exact` checks (the caller checks each frame's
    descriptors once, e.g. when describing it): other float32 descriptors would be
    matched with rounded distances.

    Run it with the BLAS limited to one thread inside a thread pool (the
    :class:`~photonpano.executor.ThreadExecutor` does): OpenBLAS's own threads,
    called from two threads at once, ran it 2.4x slower.
    """

    @staticmethod
    def exact(descriptors: NDArray) -> bool:
        """Whether the (K, D) float32 descriptors are integers whose squared distances are exact in float32."""
        d = np.asarray(descriptors)
        if d.ndim != 2 or d.dtype != np.float32 or not d.size:
            return False
        low, high = float(d.min()), float(d.max())
        return low >= 0 and 2 * d.shape[1] * high * high < 2 ** 24 and bool(np.array_equal(d, np.rint(d)))

    def ratio_matches(self, descriptors_query: NDArray, descriptors_train: NDArray,
                      ratio: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """:func:`ratio_matches` for (Kq, D) and (Kt, D) float32 descriptors that are :meth:`exact`."""
        q, t = np.asarray(descriptors_query, np.float32), np.asarray(descriptors_train, np.float32)
        if len(t) < 2:  # knnMatch's rule: no second neighbour, no match
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        squared = q @ t.T
        squared *= -2
        squared += np.einsum("ij,ij->i", t, t)[None]
        squared += np.einsum("ij,ij->i", q, q)[:, None]
        rows = np.arange(len(q))
        nearest = squared.argmin(axis=1)
        first = squared[rows, nearest]
        squared[rows, nearest] = np.inf
        second = squared.min(axis=1)
        # distances as OpenCV's (float32 square roots), compared in double as the knnMatch path is
        keep = np.sqrt(first).astype(np.float64) < ratio * np.sqrt(second).astype(np.float64)
        query = np.flatnonzero(keep)
        return query, nearest[query].astype(np.int64)
