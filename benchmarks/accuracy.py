"""Accuracy benchmark of issue 2: trajectory error and panorama PSNR against ground truth.

Simulates the acceptance capture from the bundled photo (254x496 frames, horizontal pan of
0.02 px/frame plus a 5 px, 30 Hz circular vibration at 100 kHz) at each light level and
reconstructs it with several variants of the pipeline:

- ``default``: the default spec (``photonpano pano``'s settings);
- ``paper``: the paper's plain settings (chain of consecutive pairs, SIFT + RANSAC with
  least-squares refinement, cubic interpolation through the keyframes);
- ``level1``: group averaging + SIFT without iterating (level 1 of the default spec).

Usage::

    python benchmarks/accuracy.py                   # 20 000 frames, flux 0.5 and 0.05
    python benchmarks/accuracy.py --frames 6000 --flux 0.5 --variants default
"""

from __future__ import annotations

import argparse
import time

from photonpano.host import PluginHost
from photonpano.pipeline import ground_truth_report, reconstruct
from photonpano.spec import apply_overrides, validate_spec

VARIANTS = {
    "default": [],
    "paper": ["pair_offsets=[1]", "locator.refine=lm", "interpolator.measurement=reference-frame",
              "resampler.anchor_ends=false"],
    "level1": ["levels=1"],
}


def main() -> None:
    """Run the benchmark and print one row per light level and variant."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--flux", type=float, nargs="+", default=[0.5, 0.05],
                        help="light levels in photons per pixel per binary frame")
    parser.add_argument("--variants", default="default,paper,level1")
    args = parser.parse_args()
    host = PluginHost()
    print(f"{'flux':>6} {'variant':>8} {'RMSE per level (px)':>28} {'PSNR':>7} {'true-H PSNR':>11} "
          f"{'gap':>6} {'time':>7}")
    for flux in args.flux:
        base = {"source": {"plugin": "simulate", "frames": args.frames, "flux": flux}}
        source = None
        for name in args.variants.split(","):
            spec = validate_spec(apply_overrides(base, VARIANTS[name]), host, origin=name)
            if source is None:
                source = spec.source.build()
            t0 = time.perf_counter()
            homographies, stats, pano, _ = reconstruct(spec, source)
            seconds = time.perf_counter() - t0
            report = ground_truth_report(source, homographies, pano, spec.panorama_subbatch_px,
                                         compositor=spec.compositor)
            levels = " ".join(f"{row['trajectory_rmse_px']:.3f}" for row in stats)
            print(f"{flux:>6} {name:>8} {levels:>28} {report['psnr_db']:>7.2f} "
                  f"{report['psnr_true_homographies_db']:>11.2f} {report['psnr_gap_db']:>6.2f} {seconds:>6.1f}s",
                  flush=True)


if __name__ == "__main__":
    main()
