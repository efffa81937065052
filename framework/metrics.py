"""Accuracy measures against ground truth: trajectory error and panorama PSNR."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry

__all__ = ["TrajectoryError", "trajectory_error", "source_trajectory_error", "psnr", "chroma_edge_error",
           "scene_on_canvas", "colour_scene_on_canvas",
           "ground_truth_report", "plot_trajectory", "trajectory_figure", "TRAJECTORY_MIN_SPAN_PX"]


@dataclass(frozen=True)
class TrajectoryError:
    """Trajectory error after the best global alignment.

    Attributes:
        rmse_px: RMSE over frames of the per-frame mean corner distance, in the
            ground truth's units: frame pixels (scene pixels when the sensor pitch is 1).
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
    found, _ = cv2.findHomography(est.reshape(-1, 2), gt.reshape(-1, 2), 0)
    g = np.eye(3) if found is None else np.asarray(found, np.float64)  # float64 already (no copy)
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


def chroma_edge_error(estimate: NDArray, truth: NDArray, mask: NDArray[np.bool_] | None = None,
                      *, edge_quantile: float = 0.9) -> float:
    """Mean chroma error of a colour image near the strong luminance edges of the truth.

    Colour fringes (false colour where a demosaic interpolates across an edge) show as
    chroma error at edges. Each channel of ``estimate`` is first scaled by its
    least-squares gain to ``truth`` (as :func:`psnr` does), both are divided by the
    truth's white (99.5th percentile), sRGB-encoded and converted to YCbCr (ITU-R
    BT.601); the error is ``mean(|dCb| + |dCr|) / 2`` over the pixels of ``mask`` whose
    Sobel gradient of the truth's Y is at or above its ``edge_quantile`` over ``mask``.

    Args:
        estimate: (H, W, 3) float linear R, G, B; NaN marks unobserved pixels.
        truth: (H, W, 3) float linear R, G, B ground truth.
        mask: (H, W) bool pixels to compare (default: all).
        edge_quantile: share of the compared pixels below the edge threshold.

    Returns:
        The error as a fraction of full scale (0 perfect; 1/255 is one 8-bit code).

    Raises:
        ValueError: if the images are not (H, W, 3) of one shape or no pixel is comparable.
    """
    import cv2

    from .photons import linear_to_srgb

    e, t = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    if e.shape != t.shape or e.ndim != 3 or e.shape[2] != 3:
        raise ValueError(f"chroma_edge_error: expected two (H, W, 3) images, got {e.shape} and {t.shape}")
    keep = np.asarray(np.isfinite(e).all(-1) & np.isfinite(t).all(-1))  # an array (no copy), typed as one
    if mask is not None:
        keep &= mask
    if not keep.any():
        raise ValueError("chroma_edge_error: no pixel is observed in both images")
    gains = [np.dot(e[..., c][keep], t[..., c][keep]) / max(np.dot(e[..., c][keep], e[..., c][keep]), 1e-300)
             for c in range(3)]
    white = max(float(np.percentile(t[keep], 99.5)), 1e-300)
    ycc = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
    e_ycc = linear_to_srgb(np.where(keep[..., None], e * gains, 0) / white) @ ycc.T
    t_ycc = linear_to_srgb(np.where(keep[..., None], t, 0) / white) @ ycc.T
    y = np.ascontiguousarray(t_ycc[..., 0], np.float32)
    grad = np.hypot(cv2.Sobel(y, cv2.CV_32F, 1, 0), cv2.Sobel(y, cv2.CV_32F, 0, 1))
    edges = keep & (grad >= np.quantile(grad[keep], edge_quantile))
    return float(np.abs(e_ycc[edges, 1:] - t_ycc[edges, 1:]).mean())


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
    warped = cv2.warpPerspective(scene, to_canvas, shape[::-1], flags=cv2.INTER_LANCZOS4,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return np.asarray(warped, np.float32)  # scene_flux is float32: no copy


def colour_scene_on_canvas(source, canvas_from_scene: NDArray[np.float64],
                           shape: tuple[int, int]) -> NDArray[np.float32]:
    """Resample a colour capture's true flux behind each filter onto a panorama canvas.

    :func:`scene_on_canvas` per channel of ``source.scene_flux_rgb`` (a ``simulate``
    source with ``cfa``).

    Args:
        source: a capture with ``scene_flux_rgb`` ((Hs, Ws, 3) float32 photons/s behind
            the R, G, B filters) and optionally ``scene_pitch`` (default 1).
        canvas_from_scene: (3, 3) float64 map from ground-truth coordinates to canvas pixels.
        shape: ``(Hc, Wc)`` of the canvas.

    Returns:
        (Hc, Wc, 3) float32 flux in photons/s, R, G, B; NaN outside the scene.
    """
    from types import SimpleNamespace

    pitch = getattr(source, "scene_pitch", 1.0)
    return np.stack([scene_on_canvas(SimpleNamespace(scene_flux=source.scene_flux_rgb[..., c], scene_pitch=pitch),
                                     canvas_from_scene, shape) for c in range(3)], axis=-1)


def source_trajectory_error(homographies: NDArray[np.float64], source: Any) -> TrajectoryError:
    """The :func:`trajectory_error` of ``homographies`` against the ground truth of ``source``."""
    return trajectory_error(homographies, source.ground_truth, source.width, source.height)


def ground_truth_report(source, homographies: np.ndarray, pano, subbatch_px: float, *,
                        compositor: Any = None, references: tuple[Any, ...] = (),
                        references_estimated: bool = False, progress: Any = None,
                        flicker_period_frames: float | None = None) -> dict[str, Any]:
    """Measure a reconstruction against a capture's ground truth.

    The trajectory error is taken after the best global alignment G (the panorama's
    coordinate frame is arbitrary). For the panorama, the true homographies are carried
    into the estimated canvas through G and a second panorama is composited with them
    *on the same canvas* by the same compositor; both are compared with the true scene
    flux resampled onto that canvas, so the PSNR gap measures only what the estimated
    motion costs. A capture whose hot pixels are known (the simulator's ``hot_pixel_mask``)
    is composited here with them inpainted (:class:`~photonpano.inpainting.InpaintedSource`),
    as a run with ``hot_pixels: auto`` inpaints those it finds: the reference is then the
    best merge of those photons, not one streaked by the defects.

    Args:
        source: a capture with ``ground_truth`` (and ``scene_flux`` for the PSNR;
            ``scene_pitch`` scene pixels per ground-truth unit, default 1).
        homographies: (T, 3, 3) float64 estimated frame-to-panorama homographies.
        pano: the estimated :class:`~photonpano.compose.Panorama`.
        subbatch_px: sub-batch tolerance used for the reference panorama.
        compositor: the compositor config that made ``pano`` (built afresh for the
            reference); None: the bilinear ``flux-canvas`` merge.
        references: more compositor configs to composite the true motion with on the
            same canvas, scored on the same pixels (e.g. ``flux-canvas`` to measure
            what drizzle gains).
        references_estimated: also composite each reference with the *estimated*
            homographies on the same canvas (what another compositor would have made of
            the same run).
        progress: called with the number of binary frames composited into the true-motion
            reference.
        flicker_period_frames: the flicker period (binary frames) the run's compositor was
            told of (``run.json``'s ``flicker.period_frames``), told to every compositor built
            here alike (:meth:`~photonpano.stages.Compositor.expect_flicker`); None: none.

    Returns:
        ``{"trajectory_rmse_px", "trajectory_max_px"}`` and, with a scene, ``"psnr_db",
        "psnr_true_homographies_db", "psnr_gap_db"`` and, with ``references``,
        ``"psnr_true_homographies_by"``: plugin key -> PSNR in dB (and with
        ``references_estimated``, ``"psnr_estimated_by"`` the same for the estimated
        homographies).
    """
    import cv2

    from .compose import BilinearCompositor, compose

    err = source_trajectory_error(homographies, source)
    report: dict[str, Any] = {"trajectory_rmse_px": err.rmse_px,
                              "trajectory_max_px": float(err.per_frame_px.max())}
    if source.scene_flux is None:
        return report
    canvas_from_scene = canvas_from_scene_homography(homographies, pano.homographies, err)
    shape = pano.flux.shape

    def build(config: Any) -> Any:
        built = config.build() if config is not None else BilinearCompositor()
        if flicker_period_frames is not None:
            built.expect_flicker(flicker_period_frames)
        return built

    photons = source
    if getattr(source, "hot_pixel_mask", None) is not None:  # the sensor's known defects, as a run inpaints them
        from .inpainting import InpaintedSource

        photons = InpaintedSource(source, source.hot_pixel_mask)
    truths = [compose(photons, canvas_from_scene @ source.ground_truth, build(config), subbatch_px=subbatch_px,
                      canvas_shape=shape, progress=progress if config is compositor else None)
              for config in (compositor, *references)]
    others = [compose(photons, pano.homographies, build(config), subbatch_px=subbatch_px, canvas_shape=shape)
              for config in references] if references_estimated else []
    scene = scene_on_canvas(source, canvas_from_scene, shape)
    both = np.isfinite(pano.flux) & np.isfinite(scene)
    for truth in truths + others:
        both &= np.isfinite(truth.flux)
    mask = cv2.erode(both.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    estimated_db, true_db = psnr(pano.flux, scene, mask), psnr(truths[0].flux, scene, mask)
    report.update(psnr_db=estimated_db, psnr_true_homographies_db=true_db, psnr_gap_db=true_db - estimated_db)
    if references:
        report["psnr_true_homographies_by"] = {config.plugin: psnr(truth.flux, scene, mask)
                                               for config, truth in zip(references, truths[1:])}
    if others:
        report["psnr_estimated_by"] = {config.plugin: psnr(other.flux, scene, mask)
                                       for config, other in zip(references, others)}
    return report


def canvas_from_scene_homography(homographies: np.ndarray, to_canvas: np.ndarray, error) -> np.ndarray:
    """(3, 3) homography from ground-truth scene coordinates to the panorama canvas.

    ``homographies`` map frames to the middle frame's coordinates, ``to_canvas`` the same
    frames to the canvas; ``error.alignment`` maps the former to the scene.
    """
    canvas_from_pano = to_canvas[0] @ np.linalg.inv(homographies[0])
    return canvas_from_pano @ np.linalg.inv(error.alignment)


TRAJECTORY_MIN_SPAN_PX = 1.0
"""Smallest span of a position axis of ``trajectory.png``, in canvas pixels: a static
clip's sub-pixel jitter is drawn as jitter, not stretched over the whole panel."""


def plot_trajectory(path: Path, homographies: np.ndarray, to_canvas: np.ndarray, source, error,
                    uncertainty: np.ndarray | None = None) -> None:
    """Plot the frame centres over time in canvas pixels, the predicted and (if known) actual per-frame error.

    Writes :func:`trajectory_figure` as a PNG (100 dpi).

    Args:
        path: the PNG to write.
        homographies: (T, 3, 3) frame-to-middle-frame homographies (the estimate's gauge).
        to_canvas: (T, 3, 3) frame-to-canvas homographies (``homographies.npy``).
        source: the capture (frame size, frame rate, ground truth).
        error: the :class:`~photonpano.metrics.TrajectoryError` of the estimate, or None.
        uncertainty: (T,) float64 predicted 1-sigma error per frame in pixels
            (:mod:`photonpano.uncertainty`), drawn as a band from 0 to 2 sigma, or None.
    """
    import matplotlib.pyplot as plt

    fig = trajectory_figure(homographies, to_canvas, source, error, uncertainty)
    try:
        fig.savefig(path, dpi=100)
    finally:
        plt.close(fig)


def trajectory_figure(homographies: np.ndarray, to_canvas: np.ndarray, source, error,
                      uncertainty: np.ndarray | None = None) -> Any:
    """The matplotlib figure of :func:`plot_trajectory` (the caller closes it).

    The x and y panels show the centre of each frame in canvas pixels against time in
    seconds, in plain numbers (no offset label) and over at least
    :data:`TRAJECTORY_MIN_SPAN_PX` around the data's middle, so that a static clip's
    jitter looks like jitter. Arguments as :func:`plot_trajectory`.

    Returns:
        A ``matplotlib.figure.Figure`` with 2 panels (x, y), or 3 with the error panel
        (when ``error`` or ``uncertainty`` is given).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from . import geometry

    centre = np.array([[(source.width - 1) / 2, (source.height - 1) / 2]])
    t = np.arange(len(to_canvas)) / source.frame_rate_hz
    panels = 3 if error is not None or uncertainty is not None else 2
    fig, axes = plt.subplots(panels, 1, figsize=(8, 2.2 * panels + 0.6), sharex=True)
    est = geometry.apply(to_canvas, centre)[:, 0]
    truth = None
    if error is not None:
        from_scene = canvas_from_scene_homography(homographies, to_canvas, error)
        truth = geometry.apply(from_scene @ source.ground_truth, centre)[:, 0]
    for axis, name in enumerate("xy"):
        if truth is not None:
            axes[axis].plot(t, truth[:, axis], color="0.6", lw=3, label="true")
        axes[axis].plot(t, est[:, axis], color="C0", lw=1, label="estimated")
        axes[axis].set_ylabel(f"centre {name} (canvas px)")
        axes[axis].ticklabel_format(axis="y", useOffset=False, style="plain")
        shown = np.concatenate([est[:, axis]] + ([truth[:, axis]] if truth is not None else []))
        _at_least_span(axes[axis], shown[np.isfinite(shown)], TRAJECTORY_MIN_SPAN_PX)
    axes[0].legend(loc="best")
    if uncertainty is not None:
        band = np.where(np.isfinite(uncertainty), 2 * uncertainty, np.nan)
        axes[2].fill_between(t, 0, band, color="C1", alpha=0.3, lw=0, label="predicted 2 sigma")
    if error is not None:
        axes[2].plot(t, error.per_frame_px, color="C3", lw=1, label="actual")
        axes[2].set_title(f"per-frame mean corner error after global alignment (RMSE {error.rmse_px:.3f} px)",
                          fontsize=9)
    if panels == 3:
        axes[2].set_ylabel("error (px)")
        axes[2].set_ylim(bottom=0)
        axes[2].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    return fig


def _at_least_span(ax: Any, values: np.ndarray, span: float) -> None:
    """Widen ``ax``'s y range to ``span`` around the middle of ``values`` where they span less."""
    if values.size == 0:
        return
    low, high = float(values.min()), float(values.max())
    if high - low < span:
        middle = (low + high) / 2
        ax.set_ylim(middle - span / 2, middle + span / 2)
