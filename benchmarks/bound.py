"""How precisely the photons of a capture can pin a frame's homography: the Cramer-Rao bound.

For the evaluation suite's photographs (``benchmarks/suite.py``) and light levels, the
Fisher information that N binary frames carry about the 8 parameters of a frame's
homography, and from its inverse the smallest RMS error of the frame's corners any
unbiased estimator can reach from those N frames alone (Kay, *Fundamentals of Statistical
Signal Processing: Estimation Theory*, 1993, Sec. 3.7). A frame pixel x records a 1 with
probability ``p = 1 - exp(-flux I(H x))`` (paper Eq. 2; ``I`` the scene's linear intensity
in [0, 1], ``flux`` photons per pixel per binary frame where the scene is white), so one
binary frame's information is

    F = sum_x (dp/dtheta)(dp/dtheta)^T / (p (1 - p)),   dp/dtheta = flux exp(-flux I) dI/dtheta,

with ``theta`` a small homography about the frame centre, ``x' = x + a x + b y + t_x -
x (g x + h y)`` and ``y' = y + c x + d y + t_y - y (g x + h y)``. N frames at nearly the same
pose carry N F. The bound of the corner error is ``sqrt(mean_c trace(M_c F^-1 M_c^T)) /
sqrt(N)`` (``M_c`` the corner's Jacobian), in pixels; the frame centre's shift is bounded
alike. It is averaged over three frames along the suite's base pan (frames 2 000, 10 000
and 18 000 of 20 000).

The bound is a yardstick, not a target: it counts every photon at its exact position,
through the simulator's sharp scene (a real lens blurs it). Read it as: the trajectory
error of a frame cannot fall below the printed figure unless about N frames' photons are
pooled for it.

How many frames a trajectory can pool is what ``--trajectory`` answers
(:func:`trajectory_bound`): the whole capture's path as cubic splines, the frame's shift
with knots every ``--shift-spacing`` frames (close enough to follow the suite's 30 Hz
vibration: 400 frames leave it 0.002 px of model error, 800 frames 0.05) and the other six
parameters (rotation, scale, shear, keystone) with knots every ``--rest-spacing`` frames.
The bound of such a trajectory from every frame's photons, plus the splines' own misfit
to the true path, is the least corner RMSE an unbiased estimator of that model reaches
(one that knows the scene: an estimator that builds a panorama too does worse). A
tolerance the bound exceeds at every spacing is out of reach of the photons; one that it
meets only with the six parameters nearly constant needs an estimator that assumes
little rotation, zoom or keystone change over thousands of frames.

Usage::

    python benchmarks/bound.py                              # every suite photo, flux 0.5 and 0.05
    python benchmarks/bound.py --photos city_madison,interior_clock --flux 0.5 --frames 300
    python benchmarks/bound.py --trajectory --photos highcontrast_sunset --flux 0.05
    python benchmarks/bound.py --trajectory --folder /tmp/outside --flux 0.05   # the outside check's photos
    python benchmarks/bound.py --trajectory --photos interior_clock --flux 0.5 --set frames=100000
        --set path=zigzag --set sweep_px=40 --set sweep_period_frames=20000 --set speed_px_per_frame=0.004
        # (one line) performance.py's 100 000-frame zigzag
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy import sparse

sys.path.insert(0, str(Path(__file__).resolve().parent))

WIDTH, HEIGHT = 496, 254
"""The suite's frame size in pixels."""
THETA_P = [0, 2, 4, 1, 3, 5, 6, 7]
"""Theta's parameters (a, b, t_x, c, d, t_y, g, h) as columns of p1..p8 about the frame centre
(:func:`photonpano.geometry.params_from_homographies`: a = p1, b = p3, t_x = p5, ...)."""


def frame_information(scene: np.ndarray, to_scene: np.ndarray, fluxes: list[float],
                      gradients: tuple[np.ndarray, np.ndarray] | None = None, dark: float = 0.0) -> np.ndarray:
    """Fisher information of one binary frame about its homography, at each flux.

    Args:
        scene: (Hs, Ws) float32 linear scene intensity in [0, 1].
        to_scene: (3, 3) float64 frame-to-scene homography of the frame (frame pixels to
            scene pixels).
        fluxes: photons per pixel per binary frame where the scene is white.
        gradients: the scene's (x, y) central differences, float32 like ``scene`` (computed
            when None; pass them to share them over many frames).
        dark: dark counts per pixel per binary frame (the simulator's ``dark_count_rate``:
            ``p = 1 - exp(-(flux I + dark))``). Without them a pixel of a black region next
            to an edge carries unbounded information (``p`` -> 0 there), and so the bound of
            a photograph with black regions falls toward 0.

    Returns:
        (len(fluxes), 8, 8) float64 information about theta (the module's small homography
        about the frame centre, in frame pixels), per binary frame.
    """
    import cv2
    from photonpano import geometry

    if gradients is None:
        gradients = scene_gradients(scene)
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    points = geometry.apply(to_scene, np.stack([xs.ravel(), ys.ravel()], 1)).reshape(HEIGHT, WIDTH, 2)
    scene_xy = points.astype(np.float32)
    intensity, ix, iy = (cv2.remap(image, scene_xy[..., 0], scene_xy[..., 1], cv2.INTER_LINEAR)
                         for image in (scene, *gradients))
    # d(scene point)/d(frame point) of the homography at each pixel (chain rule for turned or scaled frames)
    h = to_scene / to_scene[2, 2]
    depth = (h[2, 0] * xs + h[2, 1] * ys + h[2, 2])[..., None]
    along_x = (h[0, :2] - points[..., :1] * h[2, :2]) / depth  # (H, W, 2): dX/dx, dX/dy
    along_y = (h[1, :2] - points[..., 1:] * h[2, :2]) / depth
    xc, yc = xs - (WIDTH - 1) / 2, ys - (HEIGHT - 1) / 2
    motion_x, motion_y = _motion_x(xc, yc), _motion_y(xc, yc)  # (H, W, 8) frame point per theta
    jacobian = (ix[..., None] * (along_x[..., :1] * motion_x + along_x[..., 1:] * motion_y)
                + iy[..., None] * (along_y[..., :1] * motion_x + along_y[..., 1:] * motion_y))  # dI/dtheta
    out = []
    for flux in fluxes:
        expected = flux * intensity + dark
        p = 1 - np.exp(-expected)
        weight = (flux * np.exp(-expected)) ** 2 / np.maximum(p * (1 - p), 1e-12)
        out.append(np.einsum("hwi,hwj,hw->ij", jacobian, jacobian, weight))
    return np.array(out)


def scene_gradients(scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scene's x and y central differences, float32 (H, W) each."""
    import cv2

    return cv2.Sobel(scene, cv2.CV_32F, 1, 0, ksize=1) * 0.5, cv2.Sobel(scene, cv2.CV_32F, 0, 1, ksize=1) * 0.5


def corner_jacobians() -> np.ndarray:
    """(4, 2, 8) float64: each frame corner's move per unit of theta (about the frame centre)."""
    from photonpano import geometry

    corners = geometry.corners(WIDTH, HEIGHT) - np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2])
    return np.array([np.stack([_motion_x(np.float64(cx), np.float64(cy)), _motion_y(np.float64(cx), np.float64(cy))])
                     for cx, cy in corners])


def corner_and_shift_bound(scene: np.ndarray, to_scene: np.ndarray, flux: float) -> tuple[float, float]:
    """Cramer-Rao bound of one binary frame's corners and centre from its photons.

    Args:
        scene: (Hs, Ws) float32 linear scene intensity in [0, 1].
        to_scene: (3, 3) float64 frame-to-scene homography of the frame (a translation
            for the suite's base path, so scene and frame axes agree).
        flux: photons per pixel per binary frame where the scene is white.

    Returns:
        ``(corner, shift)``: the RMS over the four corners, and the bound of the centre's
        shift, in pixels, for one binary frame (divide by sqrt(N) for N frames).
    """
    covariance = np.linalg.inv(frame_information(scene, to_scene, [flux])[0])
    traces = [np.trace(m @ covariance @ m.T) for m in corner_jacobians()]
    return float(np.sqrt(np.mean(traces))), float(np.sqrt(covariance[2, 2] + covariance[5, 5]))


def spline_basis(n_frames: int, spacing: float | None) -> sparse.csr_array:
    """(T, K) cubic B-spline basis over frames 0..T-1, knots ``spacing`` frames apart (None: one constant)."""
    from scipy import sparse
    from scipy.interpolate import BSpline

    if spacing is None:
        return sparse.csr_array(np.ones((n_frames, 1)))
    inner = np.linspace(0, n_frames - 1, max(int(round((n_frames - 1) / spacing)), 1) + 1)
    knots = np.r_[[inner[0]] * 3, inner, [inner[-1]] * 3]
    return sparse.csr_array(BSpline.design_matrix(np.arange(n_frames, dtype=np.float64), knots, 3))


def trajectory_bound(information: np.ndarray, sampled: np.ndarray, to_scene: np.ndarray,
                     spacings: list[float | None], evaluate: int = 1000) -> tuple[float, float]:
    """The smallest corner RMSE of a trajectory estimated as splines, from every frame's photons.

    Each of theta's 8 parameters is a cubic B-spline over the frames (knots
    ``spacings[i]`` frames apart; None: constant over the capture). The spline
    coefficients' Fisher information is ``J = sum_t D_t' F_t D_t`` (``D_t`` the (8, K)
    basis at frame t, ``F_t`` the frame's information); any unbiased estimate of them has a
    covariance of at least ``J^-1`` (Kay 1993, Sec. 3.8), so each frame's homography
    one of at least ``D_t J^-1 D_t'``. The error is counted as the trajectory RMSE counts it
    (:func:`photonpano.metrics.trajectory_error`): up to one homography of the whole
    panorama, so the part of each frame's corner error that one such homography explains
    over the evaluated frames is projected out. The scene is taken as known: an estimator
    that also estimates the scene (a panorama) can only do worse. The splines also cannot
    follow the true path exactly: their least-squares fit (frame-to-scene parameters about
    the middle frame), aligned the same way, leaves a *model error*, which an estimator of
    that model has on top of its noise.

    Args:
        information: (S, 8, 8) float64 information per binary frame at ``sampled`` frames
            (:func:`frame_information`); each frame takes its nearest sample's.
        sampled: (S,) int64 increasing frame indices.
        to_scene: (T, 3, 3) float64 true frame-to-scene homographies.
        spacings: 8 knot spacings in frames (or None), one per parameter of theta
            (a, b, t_x, c, d, t_y, g, h: :func:`_motion_x`).
        evaluate: frames at which the bound is evaluated (evenly spread).

    Returns:
        ``(noise, model)``: the bound's RMS corner error over the frames, and the splines'
        RMS corner model error, in pixels; an estimator of the model reaches at best
        ``sqrt(noise^2 + model^2)``.
    """
    from photonpano import geometry
    from photonpano.metrics import trajectory_error

    n = len(to_scene)
    bases = [spline_basis(n, s) for s in spacings]
    nearest = np.clip(np.searchsorted((sampled[1:] + sampled[:-1]) / 2, np.arange(n)), 0, len(sampled) - 1)
    offsets = np.cumsum([0] + [b.shape[1] for b in bases])
    total = np.zeros((offsets[-1], offsets[-1]))
    for i in range(8):
        for k in range(i, 8):
            block = (bases[i].T @ (bases[k].multiply(information[nearest, i, k][:, None]))).toarray()
            total[offsets[i]:offsets[i + 1], offsets[k]:offsets[k + 1]] = block
            total[offsets[k]:offsets[k + 1], offsets[i]:offsets[i + 1]] = block.T
    covariance = np.linalg.inv(total)
    frames = np.unique(np.linspace(0, n - 1, min(evaluate, n)).round().astype(np.int64))
    m = corner_jacobians().reshape(8, 8)  # (corner and axis, theta)
    # each evaluated frame's corner moves per coefficient: (E * 8, K)
    moves = np.concatenate([m[None, :, i, None] * b[frames].toarray()[:, None, :] for i, b in enumerate(bases)],
                           axis=2).reshape(len(frames) * 8, -1)
    # the corner moves one global homography of the panorama makes (the metric's alignment)
    gauge = np.einsum("ci,fik->fck", m, _panorama_moves(to_scene[frames])).reshape(len(frames) * 8, 8)
    aligned = moves - gauge @ (np.linalg.pinv(gauge) @ moves)
    noise = np.einsum("rk,kl,rl->", aligned, covariance, aligned) / (len(frames) * 4)
    # model error: each frame-to-scene parameter about the middle frame fitted by the splines
    middle = to_scene[n // 2]
    params = geometry.params_from_homographies(geometry.normalize(np.linalg.inv(middle) @ to_scene))
    fitted = np.empty_like(params)
    for basis, column in zip(bases, THETA_P):
        fitted[:, column] = basis @ _least_squares(basis, params[:, column])
    model = trajectory_error(middle @ geometry.homographies_from_params(fitted), to_scene, WIDTH, HEIGHT).rmse_px
    return float(np.sqrt(noise)), float(model)


def _panorama_moves(to_scene: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """(F, 8, 8): each frame's theta per unit of each of p1..p8 of one homography of the whole panorama.

    A homography ``G`` of the panorama moves frame t by ``inv(H_t) G H_t``; its theta about the
    frame centre, per ``step`` of each parameter of ``G`` (a first-order difference).
    """
    from photonpano import geometry

    moves = np.empty((len(to_scene), 8, 8))
    inverse = np.linalg.inv(to_scene)
    for k in range(8):
        generator = geometry.homographies_from_params(step * np.eye(8)[k][None])[0]
        moved = geometry.about_centre(geometry.normalize(inverse @ generator @ to_scene), WIDTH, HEIGHT)
        moves[:, :, k] = geometry.params_from_homographies(moved)[:, THETA_P] / step
    return moves


def _least_squares(basis: sparse.csr_array, values: np.ndarray) -> np.ndarray:
    """Coefficients of the least-squares fit of ``values`` (T,) by the columns of ``basis`` (T, K)."""
    normal = (basis.T @ basis).toarray()
    return np.linalg.solve(normal, basis.T @ values)


def _motion_x(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivative of x' with respect to theta = (a, b, t_x, c, d, t_y, g, h): (..., 8)."""
    zero, one = np.zeros_like(x), np.ones_like(x)
    return np.stack([x, y, one, zero, zero, zero, -x * x, -x * y], -1)


def _motion_y(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivative of y' with respect to theta: (..., 8)."""
    zero, one = np.zeros_like(x), np.ones_like(x)
    return np.stack([zero, zero, zero, x, y, one, -x * y, -y * y], -1)


def main(argv: list[str] | None = None) -> int:
    """Print the bound per photo and flux (or, with ``--trajectory``, per knot spacing)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", default="", help="comma-separated photo stems (default: every suite photo)")
    parser.add_argument("--folder", type=Path, default=None,
                        help="take the photos from this folder instead of the suite's (as suite.py --photos)")
    parser.add_argument("--flux", default="0.5,0.05", help="comma-separated fluxes (photons/pixel/frame)")
    parser.add_argument("--frames", type=int, default=1000, help="N, the binary frames pooled (default 1000)")
    parser.add_argument("--trajectory", action="store_true",
                        help="the bound of a whole capture's trajectory as splines (the suite's base capture, "
                             "changed by --set)")
    parser.add_argument("--shift-spacing", type=float, default=400.0,
                        help="with --trajectory: knot spacing of the frame's shift, in frames (default 400)")
    parser.add_argument("--rest-spacing", default="800,1600,3200,6400,constant",
                        help="with --trajectory: knot spacings of the other six parameters, in frames "
                             "(constant: one value over the capture)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="with --trajectory: a simulate setting over the base capture's (repeatable)")
    args = parser.parse_args(argv)
    from suite import photos

    fluxes = [float(f) for f in args.flux.split(",")]
    chosen = [p for p in photos(args.folder) if not args.photos or p.stem in args.photos.split(",")]
    if args.trajectory:
        rest = [None if r == "constant" else float(r) for r in args.rest_spacing.split(",")]
        return _trajectory_table(chosen, fluxes, args.shift_spacing, rest, args.set)
    from photonpano.plugins.sources._simulated_scene import camera_path, load_scene
    from photonpano.plugins.sources.simulate import SimulateConfig

    print(f"Cramer-Rao bound from {args.frames} binary frames, RMS corner / centre shift error (px)")
    print(f"{'photo':22s} " + " ".join(f"{'flux ' + format(f, 'g'):>18s}" for f in fluxes))
    for photo in chosen:
        config = SimulateConfig(photo=photo, frames=20_000)
        scene = load_scene(photo, config.scene_width).astype(np.float32)
        path = camera_path(config, scene.shape[:2])
        row = []
        for flux in fluxes:
            bounds = np.array([corner_and_shift_bound(scene, path[t], flux) for t in (2000, 10_000, 18_000)])
            corner, shift = bounds.mean(axis=0) / np.sqrt(args.frames)
            row.append(f"{corner:8.4f} / {shift:6.4f}  ")
        print(f"{photo.stem:22s} " + " ".join(row), flush=True)
    return 0


def _trajectory_table(chosen: list[Path], fluxes: list[float], shift_spacing: float, rest: list[float | None],
                      overrides: list[str], samples: int = 400) -> int:
    """Print :func:`trajectory_bound` per photo, flux and knot spacing of the six parameters besides the shift."""
    from photonpano.plugins.sources._simulated_scene import camera_path, load_scene
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.spec import apply_overrides
    from suite import Capture

    print(f"Cramer-Rao bound of a trajectory of cubic splines, the frame's shift with knots every {shift_spacing:g} "
          "frames:\nRMS corner error (px) from the photons (noise), of the splines' fit to the true path (model), "
          "and both")
    print(f"{'capture':34s} {'other six knots every':>22s} {'noise':>7s} {'model':>7s} {'both':>7s}")
    for photo in chosen:
        settings = apply_overrides(Capture(photo, "base").source_spec(), overrides)
        settings.pop("plugin")
        config = SimulateConfig(**settings)
        if config.pixel_pitch != 1:
            raise SystemExit(f"--set pixel_pitch={config.pixel_pitch}: the bound takes frame pixels to sample the "
                             "scene at its own resolution (pixel_pitch 1)")
        scene = load_scene(photo, config.scene_width).astype(np.float32)
        if config.mean_intensity is not None:
            scene = np.minimum(scene * np.float32(config.mean_intensity / max(float(scene.mean()), 1e-12)), 1)
        path = camera_path(config, scene.shape[:2])
        gradients = scene_gradients(scene)
        sampled = np.unique(np.linspace(0, len(path) - 1, min(samples, len(path))).round().astype(np.int64))
        information = np.array([frame_information(scene, path[t], fluxes, gradients, config.dark_count_rate)
                                for t in sampled])
        for f, flux in enumerate(fluxes):
            name = f"{photo.stem} {len(path)} fr, flux {flux:g}"
            for spacing in rest:
                each = [spacing, spacing, shift_spacing, spacing, spacing, shift_spacing, spacing, spacing]
                noise, model = trajectory_bound(information[:, f], sampled, path, each)
                knots = "constant" if spacing is None else f"{spacing:g} frames"
                print(f"{name:34s} {knots:>22s} {noise:7.4f} {model:7.4f} {np.hypot(noise, model):7.4f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
