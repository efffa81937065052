"""Colour benchmark of issue 32: demosaic through motion against per-frame demosaic, then merge.

Each colour photo is simulated as a SwissSPAD2 colour half array (``simulate`` with
``cfa: colorspad``: the real filter layout, R, G or B on one pixel in four, filter
transmission 1/3), a pan of 80 scene px plus a 3 px, 30 Hz circular vibration; the
motion is estimated by the default pipeline from the luminance (filtered pixels
inpainted). On the estimated panorama's canvas (the true homographies carried onto it
through the best global alignment, as ``ground_truth_report`` does), with the spec's
compositor (``drizzle``, noise-adaptive, scale 1):

- ``motion true-H`` / ``motion est-H``: demosaic through motion
  (:class:`~photonpano.plugins.compositors.colour.CfaChannels`: each detection splatted
  into its own colour plane), with the true homographies, and the run's own colour
  panorama (``colour_panorama: true``, the estimated homographies);
- ``frame-dm r2`` / ``r3``: the baseline (:class:`~photonpano.plugins.compositors.colour.FrameDemosaic`):
  each sub-batch's sparse colour plane interpolated to every frame pixel (normalised
  convolution with a tent of half-width 2 or 3 frame pixels, the irregular layout's
  bilinear interpolation), then merged with the true homographies.

Columns: PSNR in dB per channel R/G/B against the true colour scene flux on the canvas
(``psnr`` with a gain fit, ``scene_on_canvas``), all on the same pixels (observed by
every method, eroded by 7 px); ``chroma``: :func:`~photonpano.metrics.chroma_edge_error`
(mean |dCb|+|dCr| / 2 on the 10 % strongest luminance edges, in 8-bit codes); ``gain``:
mean PSNR of ``motion est-H`` minus the better baseline's. Target: gain >= 2 dB.

Usage::

    python benchmarks/colour.py
    python benchmarks/colour.py --photos city_madison,foliage_dandelions --frames 40000 --flux 1
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
from photonpano.compose import compose
from photonpano.host import PluginHost
from photonpano.metrics import (
    canvas_from_scene_homography,
    chroma_edge_error,
    psnr,
    scene_on_canvas,
    source_trajectory_error,
)
from photonpano.pipeline import reconstruct
from photonpano.plugins.compositors.colour import CfaChannels, FrameDemosaic
from photonpano.spec import apply_overrides, validate_spec

PHOTOS = Path(__file__).parent / "photos"


def colour_scene_on_canvas(source, canvas_from_scene: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(Hc, Wc, 3) float32 true flux behind each filter on the canvas (``scene_on_canvas`` per channel)."""
    return np.stack([scene_on_canvas(SimpleNamespace(scene_flux=source.scene_flux_rgb[..., c],
                                                     scene_pitch=source.scene_pitch), canvas_from_scene, shape)
                     for c in range(3)], axis=-1)


def score(panos: dict[str, np.ndarray], truth: np.ndarray) -> dict[str, tuple[list[float], float]]:
    """Per-channel PSNR and chroma edge error of each panorama on the pixels all observe."""
    both = np.isfinite(truth).all(-1)
    for pano in panos.values():
        both &= np.isfinite(pano).all(-1)
    mask = cv2.erode(both.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    return {name: ([psnr(pano[..., c], truth[..., c], mask) for c in range(3)],
                   255 * chroma_edge_error(pano, truth, mask)) for name, pano in panos.items()}


def main() -> None:
    """Run the benchmark and print one block per photo."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", default="foliage_dandelions,city_madison,animal_chelsea")
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--flux", type=float, default=2.0)
    parser.add_argument("--height", type=int, default=128)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--scene-width", type=int, default=800)
    parser.add_argument("--set", dest="overrides", nargs="*", default=[], help="extra spec settings")
    args = parser.parse_args()
    host = PluginHost()
    print(f"{'photo':>20} {'method':>14} {'PSNR R':>7} {'G':>6} {'B':>6} {'chroma':>7}")
    for name in args.photos.split(","):
        source_spec = {"plugin": "simulate", "photo": str(PHOTOS / f"{name}.jpg"), "cfa": "colorspad",
                       "frames": args.frames, "flux": args.flux, "height": args.height, "width": args.width,
                       "scene_width": args.scene_width, "speed_px_per_frame": 80 / args.frames,
                       "vibration_px": 3.0, "colour_panorama": True}
        spec = validate_spec(apply_overrides({"source": source_spec}, args.overrides), host, origin=name)
        source = spec.source.build()
        t0 = time.perf_counter()
        homographies, _, pano, _ = reconstruct(spec, source)
        seconds = time.perf_counter() - t0
        err = source_trajectory_error(homographies, source)
        canvas_from_scene = canvas_from_scene_homography(homographies, pano.homographies, err)
        true_h, shape = canvas_from_scene @ source.ground_truth, pano.flux.shape
        truth = colour_scene_on_canvas(source, canvas_from_scene, shape)
        make, sub = spec.compositor.build, spec.panorama_subbatch_px
        runs = {"motion true-H": (CfaChannels(make), true_h),
                "frame-dm r2": (FrameDemosaic(make, radius_px=2.0), true_h),
                "frame-dm r3": (FrameDemosaic(make, radius_px=3.0), true_h)}
        panos = {key: compose(source, h, comp, subbatch_px=sub, canvas_shape=shape).flux
                 for key, (comp, h) in runs.items()}
        panos = {"motion true-H": panos.pop("motion true-H"), "motion est-H": pano.colour, **panos}
        scores = score(panos, truth)
        for key, (dbs, chroma) in scores.items():
            print(f"{name:>20} {key:>14} {dbs[0]:>7.2f} {dbs[1]:>6.2f} {dbs[2]:>6.2f} {chroma:>7.2f}")
        baseline = max(np.mean(scores[k][0]) for k in ("frame-dm r2", "frame-dm r3"))
        print(f"{name:>20} gain {np.mean(scores['motion est-H'][0]) - baseline:+.2f} dB (est-H vs best baseline), "
              f"trajectory RMSE {err.rmse_px:.3f} px, reconstruction {seconds:.0f} s", flush=True)


if __name__ == "__main__":
    main()
