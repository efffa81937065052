"""Benchmark: 6-DoF poses from virtual exposures (pycolmap-sfm), naive averaging vs each level.

Simulates a ``simulate3d`` room capture (default: 20 000 binary frames, 254x496, flux
0.5, ~0.36 m path with a 30 Hz vibration) and runs ``pycolmap-sfm`` with the true
intrinsics and with self-calibration. Level 1 is the naive baseline (plain averages of m
frames). Prints, per level: exposures registered, ATE after a similarity alignment, and
the relative pose error over m frames (mm and % of the true motion over that gap).

    python benchmarks/pose.py [--frames 20000] [--group-size 1000] [--levels 4] [--photo PATH ...]
        [--source key=value ...] [--set key=value ...]

``--source`` sets other ``simulate3d`` fields (e.g. ``path_m=0.3 vibration_hz=40``) and
``--set`` other ``pycolmap-sfm`` fields (e.g. ``track_window=0``), to check that the
figures hold on other scenes and paths and to compare settings.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from photonpano.host import PluginHost
from photonpano.pose_run import run_pose
from photonpano.spec import validate_spec


def main() -> None:
    """Run the benchmark and print one table per intrinsics setting."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--group-size", type=int, default=1000)
    parser.add_argument("--levels", type=int, default=3)
    parser.add_argument("--flux", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--photo", type=Path, action="append", default=[])
    parser.add_argument("--no-self-calibration", action="store_true")
    parser.add_argument("--source", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()

    def fields(pairs: list[str]) -> dict[str, str]:
        if any("=" not in pair for pair in pairs):
            parser.error(f"expected KEY=VALUE, got {pairs}")
        return dict(pair.split("=", 1) for pair in pairs)

    host = PluginHost()
    source = {
        "plugin": "simulate3d",
        "frames": args.frames,
        "flux": args.flux,
        "seed": args.seed,
        "photos": [str(p) for p in args.photo],
        **fields(args.source),
    }
    estimator = {
        "plugin": "pycolmap-sfm",
        "group_size": args.group_size,
        "levels": args.levels,
        **fields(args.set),
    }
    spec = validate_spec({"source": source, "pose_estimator": estimator}, host, origin="benchmark")
    t0 = time.perf_counter()
    room = spec.source.build()
    print(
        f"# {room.name}: {args.frames} frames {room.height}x{room.width}, simulated in "
        f"{time.perf_counter() - t0:.0f} s; source {fields(args.source)}, estimator {fields(args.set)}"
    )
    # reuse the simulated capture for both runs
    spec.source.__class__.build = lambda self, _room=room: _room  # type: ignore[method-assign]
    settings = [("true intrinsics", room.intrinsics)]
    if not args.no_self_calibration:
        settings.append(("self-calibration", None))
    for label, intrinsics in settings:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            summary, result = run_pose(spec, Path(tmp) / "out", host, intrinsics=intrinsics)
            wall = time.perf_counter() - t0
        gap = summary["ground_truth"]["rpe_gap_frames"]
        print(
            f"\n## {label} (RPE gap {gap} frames; {wall:.0f} s; intrinsics used "
            f"{ {k: round(v, 1) for k, v in result.intrinsics.as_dict().items()} })"
        )
        print(
            "| level | exposures | registered | points | reproj. px | ATE mm | exposure ATE mm "
            "| RPE mm | RPE % of motion | RPE deg | register s |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        nan = float("nan")
        for row in summary["levels"]:
            rpe = row.get("rpe", {})
            reproj = row.get("reprojection_error_px")
            print(
                f"| {row['level']}{' (naive)' if row['level'] == 1 else ''} | {row['exposures']} | "
                f"{row['registered']} | {row.get('points', '')} | "
                f"{reproj if reproj is None else f'{reproj:.2f}'} | "
                f"{1e3 * row.get('ate_m', nan):.2f} | "
                f"{1e3 * row.get('exposure_ate_m', nan):.2f} | "
                f"{1e3 * rpe.get('translation_m', nan):.2f} | {rpe.get('percent', nan):.1f} | "
                f"{rpe.get('rotation_deg', nan):.3f} | {row['timings_s']['register']:.0f} |"
            )


if __name__ == "__main__":
    main()
