"""Super-resolution benchmark of issue 12: does ``scale: 2`` resolve what the sensor cannot?

Two simulated captures, each reconstructed with the default pipeline (motion estimated
from the photons, ``drizzle`` compositor) and scored by PSNR against the true scene flux
on the panorama canvas (``ground_truth_report``):

- ``undersampled``: a sensor whose pixels are point samples 2 scene pixels apart
  (``pixel_pitch: 2``, frames of 127x248 covering 254x496 scene pixels), a pan of
  0.04 scene px/frame plus a 6 px, 30 Hz vibration, flux 0.5, 20 000 frames; panorama
  at ``scale: 2``, compared with the full-resolution scene;
- ``standard``: the acceptance capture of issue 2 (254x496 frames, pitch 1, pan 0.02
  px/frame, 5 px vibration, flux 0.5), panorama at ``scale: 1``.

Columns: PSNR of the default pipeline (estimated motion, drizzle); of drizzle with
the true motion; of the bilinear merge (``flux-canvas``) with the true motion on the
same canvas (the reference), all on the same pixels; ``gain`` = default - reference.
Acceptance: gain >= 2.5 dB undersampled at scale 2 (issue 27, on every photograph),
>= -0.3 dB standard at scale 1.
Same as ``photonpano run spec.yaml --set scale=2``.

Measured (issue 27, 2-core machine; docs/performance.md has the table and the
diagnosis): bundled photo undersampled +5.31 dB, standard +5.42 dB; undersampled
``city_madison`` +3.42, ``texture_gravel`` +2.71, ``portrait_astronaut`` +3.26 dB (the
earlier noise-adaptive blend, ``--set compositor.restoration=blend``: +2.66, +1.16,
+1.68, +1.52, +1.57 dB). Since the blur weight by scale (2026-11-28): undersampled, the
bundled photo +5.57 dB and the 15 suite photographs +2.52 to +6.72 dB; since the
sliding DCT at every block position (stride 1), +2.69 to +6.83 dB (mean +4.12), and
``standard`` +3.64 to +11.40 dB (mean +6.91).

Usage::

    python benchmarks/super_resolution.py
    python benchmarks/super_resolution.py --photo other.jpg --scene-width 1200 --captures undersampled
    python benchmarks/super_resolution.py --set compositor.noise_adaptive=false
"""

from __future__ import annotations

import argparse
import time

from photonpano.host import PluginHost
from photonpano.metrics import ground_truth_report
from photonpano.pipeline import reconstruct
from photonpano.spec import apply_overrides, validate_spec

CAPTURES = {
    "undersampled": ({"height": 127, "width": 248, "pixel_pitch": 2, "speed_px_per_frame": 0.04,
                      "vibration_px": 6.0}, 2.0, 2.5),
    "standard": ({}, 1.0, -0.3),
}
"""name -> (simulate fields, panorama scale, required gain in dB)."""


def main() -> None:
    """Run the benchmark and print one row per capture."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--flux", type=float, default=0.5)
    parser.add_argument("--photo", default=None, help="photograph to simulate (default: the bundled one)")
    parser.add_argument("--scene-width", type=int, default=1440)
    parser.add_argument("--captures", default="undersampled,standard")
    parser.add_argument("--set", dest="overrides", nargs="*", default=[],
                        help="extra spec settings, e.g. compositor.kernel=point")
    args = parser.parse_args()
    host = PluginHost()
    print(f"{'capture':>12} {'scale':>5} {'RMSE per level (px)':>20} {'default':>8} {'drizzle true-H':>14} "
          f"{'bilinear true-H':>15} {'gain':>6} {'need':>5} {'time':>6}")
    for name in args.captures.split(","):
        fields, scale, need = CAPTURES[name]
        source_spec = {"plugin": "simulate", "frames": args.frames, "flux": args.flux,
                       "scene_width": args.scene_width, **fields}
        if args.photo:
            source_spec["photo"] = args.photo
        spec = validate_spec(apply_overrides({"source": source_spec, "scale": scale}, args.overrides), host,
                             origin=name)
        source = spec.source.build()
        t0 = time.perf_counter()
        homographies, stats, pano, timings = reconstruct(spec, source)
        seconds = time.perf_counter() - t0
        subbatch_px = spec.panorama_subbatch_px
        bilinear = host.registry("compositor")["flux-canvas"](scale=scale)
        report = ground_truth_report(source, homographies, pano, subbatch_px, compositor=spec.compositor,
                                     references=(bilinear,))
        reference = report["psnr_true_homographies_by"]["flux-canvas"]
        levels = " ".join(f"{row['trajectory_rmse_px']:.3f}" for row in stats)
        gain = report["psnr_db"] - reference
        print(f"{name:>12} {scale:>5.1f} {levels:>20} {report['psnr_db']:>8.2f} "
              f"{report['psnr_true_homographies_db']:>14.2f} {reference:>15.2f} {gain:>+6.2f} {need:>+5.1f} "
              f"{seconds:>5.0f}s"
              f"  (panorama stage {timings['panorama']:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
