"""Accuracy measures against ground truth: trajectory error and panorama PSNR."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import geometry

__all__ = ["TrajectoryError", "trajectory_error", "psnr", "scene_on_canvas"]


@dataclass(frozen=True)
class TrajectoryError:
    """Trajectory error after the best global alignment.

    Attributes:
        rmse_px: RMSE over frames of the per-frame mean corner distance, in ground-truth
            (scene) pixels.
        per_frame_px: (T,) float64 mean corner distance of each frame, in pixels.
        alignment: (3, 3) float64 homography G mapping estimated panorama coordinates to
            ground-truth coordinates that minimises the corner distances.
    """

    rmse_px: float
    per_frame_px: NDArray[np.float64]
    alignment: NDArray[np.float64]


def trajectory_error(estimated: NDArray[np.float64], truth: NDArray[np.float64],
                     width: int, height: int) -> TrajectoryError:
    """Compare per-frame homographies with the truth, up to one global homography.

    The panorama's coordinate frame is arbitrary (gauge freedom), so a homography G is
    fitted (least squares on all frame corners, refined by Levenberg-Marquardt) such that
    ``G @ estimated[t]`` maps each frame's corners close to ``truth[t]``'s.

    Args:
        estimated: (T, 3, 3) float64 frame-to-panorama homographies.
        truth: (T, 3, 3) float64 frame-to-scene homographies.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        The aligned error (see :class:`TrajectoryError`).

    Raises:
        ValueError: if the stacks differ in shape.
    """
    import cv2

    if estimated.shape != truth.shape:
        raise ValueError(f"estimated {estimated.shape} and true {truth.shape} homographies differ in shape")
    c = geometry.corners(width, height)
    est = geometry.apply(estimated, c)  # (T, 4, 2)
    gt = geometry.apply(truth, c)
    g, _ = cv2.findHomography(est.reshape(-1, 2), gt.reshape(-1, 2), 0)
    if g is None:
        g = np.eye(3)
    aligned = geometry.apply(g, est.reshape(-1, 2)).reshape(est.shape)
    per_frame = np.linalg.norm(aligned - gt, axis=-1).mean(axis=-1)
    return TrajectoryError(float(np.sqrt(np.mean(per_frame ** 2))), per_frame, g / g[2, 2])


def psnr(estimate: NDArray, truth: NDArray, mask: NDArray[np.bool_] | None = None,
         *, fit_gain: bool = True) -> float:
    """Peak signal-to-noise ratio of a linear image, after an optional gain fit.

    ``PSNR = 10 log10(max(truth)^2 / MSE)`` over ``mask`` (and finite pixels). With
    ``fit_gain`` the estimate is first scaled by the least-squares gain
    ``sum(e t) / sum(e e)``, so a global exposure difference is not counted as error.

    Args:
        estimate: (H, W) float linear image; NaN marks unobserved pixels.
        truth: (H, W) float linear ground truth.
        mask: (H, W) bool pixels to compare (default: all).
        fit_gain: fit a global gain first.

    Returns:
        PSNR in dB.

    Raises:
        ValueError: if no pixel is comparable.
    """
    e = np.asarray(estimate, np.float64)
    t = np.asarray(truth, np.float64)
    keep = np.isfinite(e) & np.isfinite(t)
    if mask is not None:
        keep &= mask
    if not keep.any():
        raise ValueError("psnr: no pixel is observed in both images")
    e, t = e[keep], t[keep]
    if fit_gain:
        e = e * (np.dot(e, t) / max(np.dot(e, e), 1e-300))
    mse = np.mean((e - t) ** 2)
    return float(10 * np.log10(t.max() ** 2 / max(mse, 1e-300)))


def scene_on_canvas(source, canvas_from_scene: NDArray[np.float64],
                    shape: tuple[int, int]) -> NDArray[np.float32]:
    """Resample a capture's true scene flux onto a panorama canvas.

    Lanczos resampling (a bilinear one would blur the reference and favour blurred
    panoramas); where the canvas is coarser than the scene, the scene is area-averaged
    first (no aliasing).

    Args:
        source: a capture with ``scene_flux`` ((Hs, Ws) float32 photons/s) and
            ``scene_pitch`` (scene pixels per ground-truth unit, default 1).
        canvas_from_scene: (3, 3) float64 map from ground-truth coordinates (those
            ``source.ground_truth`` maps frames to) to canvas pixels.
        shape: ``(Hc, Wc)`` of the canvas.

    Returns:
        (Hc, Wc) float32 flux in photons/s; NaN outside the scene.
    """
    import cv2

    pitch = float(getattr(source, "scene_pitch", 1.0))
    to_canvas = canvas_from_scene @ geometry.scale_matrix(1.0 / pitch)
    scene = source.scene_flux
    step = int(np.floor(np.sqrt(abs(np.linalg.det(np.linalg.inv(to_canvas)[:2, :2])))))
    if step >= 2:  # the canvas is coarser than the scene: average the scene first (no aliasing)
        size = (scene.shape[1] // step, scene.shape[0] // step)
        scene = cv2.resize(scene, size, interpolation=cv2.INTER_AREA)
        to_canvas = to_canvas @ geometry.scale_matrix(step)
    return cv2.warpPerspective(scene, to_canvas, shape[::-1], flags=cv2.INTER_LANCZOS4,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
