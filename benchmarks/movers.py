"""The figures of docs/real_scenes.md, "Moving objects": the robust merge and ``reject_movers``.

Two measurements on captures simulated like the evaluation suite's (20 000 frames, flux 0.5,
a pan with a 5 px 30 Hz vibration; ``--photo`` a photograph, default the bundled office):

- ``merge``: the capture with and without a bright disc (radius 30 px, 0.08 px/frame)
  composited with the *true* motion on one canvas by ``drizzle`` and ``flux-canvas``, plain
  and robust; PSNR against the scene over the pixels all panoramas cover (eroded by 3 px).
  With a flickering lamp (``--simulate '{"flicker_hz": 100, ...}'``) the compositors are
  told its period, as the pipeline tells them the detected one; ``--tolerance`` sets the
  robust test's (``photonpano.robust_merge.TOLERANCE``).
- ``colour``: as ``merge``, for the colour panorama (``cfa: colorspad``, the panorama stage's
  ``ColourPanorama`` around ``drizzle``, plain and robust): mean PSNR over R, G, B against
  the true colour scene.
- ``run``: a full reconstruction with the default settings plus ``--set`` overrides; the
  trajectory RMSE, status and PSNR (``ground_truth_report``) and, with the disc, the PSNR
  of the static capture merged with the true motion by the default compositor on the
  run's canvas (the acceptance's reference).

Usage::

    python benchmarks/movers.py merge --photo benchmarks/photos/foliage_dandelions.jpg
    python benchmarks/movers.py merge --tolerance 0.25 --simulate '{"flicker_hz": 120, "flicker_region": "right"}'
    python benchmarks/movers.py colour --photo benchmarks/photos/city_madison.jpg
    python benchmarks/movers.py run --disc --set mosaic.reject_movers=5
    python benchmarks/movers.py run --photo benchmarks/photos/highcontrast_hubble.jpg --set compositor.robust=false
"""

from __future__ import annotations

import argparse
import json

import numpy as np

BASE = {"frames": 20_000, "flux": 0.5, "vibration_px": 5.0, "vibration_hz": 30.0}
DISC = {"mover_radius_px": 30.0, "mover_speed_px_per_frame": 0.08, "mover_intensity": 1.0}


def _mask(*images: np.ndarray) -> np.ndarray:
    """Pixels finite in every image, eroded by 3 px."""
    import cv2

    both = np.logical_and.reduce([np.isfinite(i) for i in images])
    return cv2.erode(both.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0


def merge(settings: dict) -> dict:
    """PSNR of the plain and robust merges, with and without the disc, with the true motion.

    Args:
        settings: ``simulate`` settings over :data:`BASE`.

    Returns:
        ``{"drizzle" | "flux-canvas": {"static" | "disc": {"plain" | "robust": dB}}}``.
    """
    from photonpano.compose import canvas_homographies, compose
    from photonpano.metrics import psnr, scene_on_canvas
    from photonpano.plugins.compositors.drizzle import DrizzleConfig
    from photonpano.plugins.compositors.flux_canvas import FluxCanvasConfig
    from photonpano.plugins.sources.simulate import SimulateConfig

    captures = {"static": SimulateConfig(**{**BASE, **settings}).build(),
                "disc": SimulateConfig(**{**BASE, **settings, **DISC}).build()}
    static = captures["static"]
    to_canvas, shape = canvas_homographies(static.ground_truth, static.width, static.height, 1.0)
    scene = scene_on_canvas(static, to_canvas[0] @ np.linalg.inv(static.ground_truth[0]), shape)
    out: dict = {}
    period = static.frame_rate_hz / static.config.flicker_hz if static.config.flicker_hz > 0 else None

    def build(config: type, robust: bool):
        compositor = config(robust=robust).build()
        if period is not None:
            compositor.expect_flicker(period)
        return compositor

    for config in (DrizzleConfig, FluxCanvasConfig):
        panos = {(name, kind): compose(capture, to_canvas, build(config, kind == "robust"), canvas_shape=shape)
                 for name, capture in captures.items() for kind in ("plain", "robust")}
        mask = _mask(scene, *(p.flux for p in panos.values()))
        result: dict = {}
        for (name, kind), pano in panos.items():
            result.setdefault(name, {})[kind] = round(psnr(pano.flux, scene, mask), 3)
            if pano.moving is not None:
                result[name]["moving_fraction"] = round(float(pano.moving.mean()), 4)
        out[config().plugin] = result
    return out


def colour(settings: dict) -> dict:
    """PSNR of the plain and robust colour panoramas, with and without the disc, with the true motion.

    Args:
        settings: ``simulate`` settings over :data:`BASE` (``cfa: colorspad`` added).

    Returns:
        ``{"static" | "disc": {"plain" | "robust": dB}}``: the mean over R, G and B of
        ``psnr`` against the true colour flux on the canvas.
    """
    from photonpano.compose import canvas_homographies, compose
    from photonpano.metrics import colour_scene_on_canvas, psnr
    from photonpano.plugins.compositors.colour import ColourPanorama
    from photonpano.plugins.compositors.drizzle import DrizzleConfig
    from photonpano.plugins.sources.simulate import SimulateConfig

    settings = {**BASE, "cfa": "colorspad", **settings}
    captures = {"static": SimulateConfig(**settings).build(), "disc": SimulateConfig(**settings, **DISC).build()}
    static = captures["static"]
    to_canvas, shape = canvas_homographies(static.ground_truth, static.width, static.height, 1.0)
    from_scene = to_canvas[0] @ np.linalg.inv(static.ground_truth[0])
    scene = colour_scene_on_canvas(static, from_scene, shape)
    panos = {(name, kind): compose(capture, to_canvas, ColourPanorama(DrizzleConfig(robust=kind == "robust").build),
                                   canvas_shape=shape).colour
             for name, capture in captures.items() for kind in ("plain", "robust")}
    mask = _mask(*(p.min(axis=-1) for p in (scene, *panos.values())))
    out: dict = {}
    for (name, kind), pano in panos.items():
        out.setdefault(name, {})[kind] = round(float(np.mean([psnr(pano[..., c], scene[..., c], mask)
                                                              for c in range(3)])), 3)
    return out


def run(settings: dict, overrides: list[str], disc: bool) -> dict:
    """One reconstruction with default settings plus ``overrides``; see the module.

    Args:
        settings: ``simulate`` settings over :data:`BASE`.
        overrides: ``--set``-style ``key=value`` strings.
        disc: add the crossing disc.

    Returns:
        RMSE, max error, status, PSNR and, with the disc, ``static_true_psnr`` and
        ``moving_fraction``.
    """
    from photonpano.compose import compose
    from photonpano.host import PluginHost
    from photonpano.metrics import (
        canvas_from_scene_homography,
        ground_truth_report,
        psnr,
        scene_on_canvas,
        source_trajectory_error,
    )
    from photonpano.plugins.compositors.drizzle import DrizzleConfig
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.reconstruction import reconstruct
    from photonpano.spec import apply_overrides, validate_spec

    source = {"plugin": "simulate", **BASE, **settings, **(DISC if disc else {})}
    spec = validate_spec(apply_overrides({"source": source}, overrides), PluginHost(), origin="movers")
    capture = spec.source.build()
    report: dict = {}
    homographies, _, pano, _ = reconstruct(spec, capture, report=report)
    gt = ground_truth_report(capture, homographies, pano, spec.panorama_subbatch_px, compositor=spec.compositor,
                             flicker_period_frames=(report.get("flicker") or {}).get("period_frames"))
    row = {"rmse_px": round(gt["trajectory_rmse_px"], 4), "max_px": round(gt["trajectory_max_px"], 3),
           "status": report["status"], "psnr_db": round(gt["psnr_db"], 3)}
    if disc:
        static = SimulateConfig(**{**BASE, **settings}).build()
        to_canvas = canvas_from_scene_homography(homographies, pano.homographies,
                                                 source_trajectory_error(homographies, capture))
        reference = compose(static, to_canvas @ static.ground_truth, DrizzleConfig().build(),
                            subbatch_px=spec.panorama_subbatch_px, canvas_shape=pano.flux.shape)
        scene = scene_on_canvas(capture, to_canvas, pano.flux.shape)
        mask = _mask(pano.flux, scene, reference.flux)
        row.update(psnr_db=round(psnr(pano.flux, scene, mask), 3),
                   static_true_psnr_db=round(psnr(reference.flux, scene, mask), 3))
        if pano.moving is not None:
            row["moving_fraction"] = round(float(pano.moving.mean()), 4)
    return row


def main(argv: list[str] | None = None) -> int:
    """Print one measurement as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["merge", "colour", "run"])
    parser.add_argument("--photo", help="a photograph (default: the bundled office)")
    parser.add_argument("--disc", action="store_true", help="run: add the crossing disc")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="run: a spec override")
    parser.add_argument("--simulate", default="{}", help="more simulate settings, as JSON")
    parser.add_argument("--tolerance", type=float, help="the robust test's tolerance (default: TOLERANCE)")
    args = parser.parse_args(argv)
    if args.tolerance is not None:
        import photonpano.robust_merge

        photonpano.robust_merge.TOLERANCE = args.tolerance
    settings = {**({"photo": args.photo} if args.photo else {}), **json.loads(args.simulate)}
    if args.what == "run":
        result = run(settings, args.overrides, args.disc)
    else:
        result = merge(settings) if args.what == "merge" else colour(settings)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
