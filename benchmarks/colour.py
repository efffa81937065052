"""Colour benchmark of issue 32: luminance-guided colour against per-plane merges and per-frame demosaic.

Each colour photo is simulated as a SwissSPAD2 colour half array (``simulate`` with
``cfa: colorspad``: the real filter layout, R, G or B on one pixel in four, filter
transmission 1/3), a pan of 80 scene px plus a 3 px, 30 Hz circular vibration; the
motion is estimated by the default pipeline from the luminance (filtered pixels
inpainted). On the estimated panorama's canvas (the true homographies carried onto it
through the best global alignment, as ``ground_truth_report`` does), with the spec's
compositor (``drizzle``, noise-adaptive, at ``--scale``, default 1):

- ``guided est-H``: the run's own colour panorama (``colour_panorama: true``, the
  estimated homographies): luminance-guided demosaic through motion
  (:class:`~photonpano.plugins.compositors.colour.LumaGuided`: sharp luminance from every
  unfiltered photon, colour ratios from the planes, the planes kept where their colour
  detail beats their noise);
- ``plane drizzle`` / ``plane bilinear``: the per-plane merge
  (:class:`~photonpano.plugins.compositors.colour.CfaChannels`: each detection splatted
  into its own colour plane, each plane merged on its own, then stacked), with the
  spec's compositor (``drizzle``) and with ``flux-canvas`` (bilinear warps: the colour
  observer of photonpano before issue 32), on the estimated homographies;
- ``frame-dm r2`` / ``r3``: per-frame demosaic, then merge
  (:class:`~photonpano.plugins.compositors.colour.FrameDemosaic`): each sub-batch's sparse
  colour plane interpolated to every frame pixel (normalised convolution with a tent of
  half-width 2 or 3 frame pixels), then merged with the estimated homographies.

The baselines read the capture as the run did (its hot and dead pixels found and left
out, ``hot_pixels``). Columns: PSNR in dB per channel R/G/B against the true colour scene flux on the canvas
(``psnr`` with a gain fit, ``scene_on_canvas``), all on the same pixels (observed by
every method, eroded by 7 px); ``chroma``: :func:`~photonpano.metrics.chroma_edge_error`
(mean |dCb|+|dCr| / 2 on the 10 % strongest luminance edges, in 8-bit codes). The last
line per photo: mean PSNR of ``guided est-H`` minus each per-plane merge's and the better
per-frame demosaic's. Target (issue 32): >= 2 dB over the per-plane merge.

Usage::

    python benchmarks/colour.py                 # all photos of benchmarks/photos
    python benchmarks/colour.py --scale 2       # super-resolved colour
    python benchmarks/colour.py --photos city_madison,foliage_dandelions --frames 40000 --flux 1
    python benchmarks/colour.py --photos city_madison --set source.hot_pixel_fraction=0.01 [hot_pixels=off]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
from photonpano.compose import compose
from photonpano.host import PluginHost
from photonpano.inpainting import InpaintedSource
from photonpano.metrics import (
    canvas_from_scene_homography,
    chroma_edge_error,
    colour_scene_on_canvas,
    psnr,
    source_trajectory_error,
)
from photonpano.pipeline import reconstruct
from photonpano.plugins.compositors.colour import CfaChannels, FrameDemosaic
from photonpano.plugins.compositors.flux_canvas import FluxCanvasConfig
from photonpano.spec import apply_overrides, validate_spec

PHOTOS = Path(__file__).parent / "photos"


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
    parser.add_argument("--photos", default=",".join(sorted(p.stem for p in PHOTOS.glob("*.jpg"))))
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--flux", type=float, default=2.0)
    parser.add_argument("--height", type=int, default=128)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--scene-width", type=int, default=800)
    parser.add_argument("--scale", type=float, default=1.0, help="compositor scale (super-resolution)")
    parser.add_argument("--set", dest="overrides", nargs="*", default=[], help="extra spec settings")
    args = parser.parse_args()
    host, scale = PluginHost(), args.scale
    print(f"{'photo':>20} {'method':>14} {'PSNR R':>7} {'G':>6} {'B':>6} {'chroma':>7}")
    for name in args.photos.split(","):
        source_spec = {"plugin": "simulate", "photo": str(PHOTOS / f"{name}.jpg"), "cfa": "colorspad",
                       "frames": args.frames, "flux": args.flux, "height": args.height, "width": args.width,
                       "scene_width": args.scene_width, "speed_px_per_frame": 80 / args.frames,
                       "vibration_px": 3.0, "colour_panorama": True}
        data = {"source": source_spec, "compositor": {"plugin": "drizzle", "scale": scale}}
        spec = validate_spec(apply_overrides(data, args.overrides), host, origin=name)
        source = spec.source.build()
        t0 = time.perf_counter()
        report: dict = {}
        homographies, _, pano, _ = reconstruct(spec, source, report=report)
        seconds = time.perf_counter() - t0
        err = source_trajectory_error(homographies, source)
        canvas_from_scene = canvas_from_scene_homography(homographies, pano.homographies, err)
        shape = pano.flux.shape
        truth = colour_scene_on_canvas(source, canvas_from_scene, shape)
        make, sub = spec.compositor.build, spec.panorama_subbatch_px
        est_h = pano.homographies
        runs = {"plane drizzle": CfaChannels(make), "plane bilinear": CfaChannels(FluxCanvasConfig(scale=scale).build),
                "frame-dm r2": FrameDemosaic(make, radius_px=2.0), "frame-dm r3": FrameDemosaic(make, radius_px=3.0)}
        panos = {"guided est-H": pano.colour}
        hot = report["hot_pixel_mask"]  # the capture as the run read it
        read = source if hot is None else InpaintedSource(source, hot)
        panos.update({key: compose(read, est_h, comp, subbatch_px=sub, canvas_shape=shape).flux
                      for key, comp in runs.items()})
        scores = score(panos, truth)
        for key, (dbs, chroma) in scores.items():
            print(f"{name:>20} {key:>14} {dbs[0]:>7.2f} {dbs[1]:>6.2f} {dbs[2]:>6.2f} {chroma:>7.2f}")
        mean = {key: float(np.mean(dbs)) for key, (dbs, _) in scores.items()}
        gains = [f"{mean['guided est-H'] - mean[k]:+.2f} dB vs {k}" for k in ("plane drizzle", "plane bilinear")]
        gains.append(f"{mean['guided est-H'] - max(mean['frame-dm r2'], mean['frame-dm r3']):+.2f} dB vs frame-dm")
        print(f"{name:>20} gain {', '.join(gains)}; trajectory RMSE {err.rmse_px:.3f} px, "
              f"reconstruction {seconds:.0f} s", flush=True)

if __name__ == "__main__":
    main()
