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
through the simulator's sharp scene (a real lens blurs it), and says nothing of how many
frames a trajectory that must follow a 30 Hz vibration can pool (the pipeline's spline
has a knot every half group, 150-400 frames). Read it as: the trajectory error of a frame
cannot fall below the printed figure unless about N frames' photons are pooled for it.

Usage::

    python benchmarks/bound.py                              # every suite photo, flux 0.5 and 0.05
    python benchmarks/bound.py --photos city_madison,interior_clock --flux 0.5 --frames 300
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

WIDTH, HEIGHT = 496, 254
"""The suite's frame size in pixels."""


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
    import cv2
    from photonpano import geometry

    gx = cv2.Sobel(scene, cv2.CV_32F, 1, 0, ksize=1) * 0.5  # central differences
    gy = cv2.Sobel(scene, cv2.CV_32F, 0, 1, ksize=1) * 0.5
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    points = geometry.apply(to_scene, np.stack([xs.ravel(), ys.ravel()], 1)).astype(np.float32)
    points = points.reshape(HEIGHT, WIDTH, 2)
    intensity, ix, iy = (cv2.remap(image, points[..., 0], points[..., 1], cv2.INTER_LINEAR)
                         for image in (scene, gx, gy))
    xc, yc = xs - (WIDTH - 1) / 2, ys - (HEIGHT - 1) / 2
    jacobian = ix[..., None] * _motion_x(xc, yc) + iy[..., None] * _motion_y(xc, yc)  # dI/dtheta, (H, W, 8)
    expected = flux * intensity
    p = 1 - np.exp(-expected)
    weight = (flux * np.exp(-expected)) ** 2 / np.maximum(p * (1 - p), 1e-12)
    covariance = np.linalg.inv(np.einsum("hwi,hwj,hw->ij", jacobian, jacobian, weight))
    corners = geometry.corners(WIDTH, HEIGHT) - np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2])
    traces = []
    for cx, cy in corners:
        m = np.stack([_motion_x(np.float64(cx), np.float64(cy)), _motion_y(np.float64(cx), np.float64(cy))])
        traces.append(np.trace(m @ covariance @ m.T))
    return float(np.sqrt(np.mean(traces))), float(np.sqrt(covariance[2, 2] + covariance[5, 5]))


def _motion_x(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivative of x' with respect to theta = (a, b, t_x, c, d, t_y, g, h): (..., 8)."""
    zero, one = np.zeros_like(x), np.ones_like(x)
    return np.stack([x, y, one, zero, zero, zero, -x * x, -x * y], -1)


def _motion_y(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivative of y' with respect to theta: (..., 8)."""
    zero, one = np.zeros_like(x), np.ones_like(x)
    return np.stack([zero, zero, zero, x, y, one, -x * y, -y * y], -1)


def main(argv: list[str] | None = None) -> int:
    """Print the bound per photo and flux."""
    from photonpano.plugins.sources._simulated_scene import camera_path, load_scene
    from photonpano.plugins.sources.simulate import SimulateConfig
    from suite import photos

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", default="", help="comma-separated photo stems (default: every suite photo)")
    parser.add_argument("--flux", default="0.5,0.05", help="comma-separated fluxes (photons/pixel/frame)")
    parser.add_argument("--frames", type=int, default=1000, help="N, the binary frames pooled (default 1000)")
    args = parser.parse_args(argv)
    fluxes = [float(f) for f in args.flux.split(",")]
    chosen = [p for p in photos() if not args.photos or p.stem in args.photos.split(",")]
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


if __name__ == "__main__":
    sys.exit(main())
