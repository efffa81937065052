"""``photonpano batch`` on a local Dask cluster against the same runs one after another (issue 15).

Four simulated captures (different seeds and camera paths, 6 000 frames of the default
254x496 each) are reconstructed twice:

- ``serial``: four ``photonpano run SPEC --set executor=serial`` processes, one after
  another;
- ``batch``: one ``photonpano batch SPEC... --set executor=dask --set workers=2``, a
  local cluster of 2 worker processes, each capture one Dask task (cluster start-up
  included in the time).

Prints both wall-clock times (and the CPU time of the processes, which a shared machine
does not change much: the load average is printed too), their ratio (acceptance: <= 0.6) and, per capture, the RMSE
of the frame corners between the batch's and the serial run's homographies (acceptance:
<= 0.05 px; the same serial pipeline runs inside each task, so 0 is expected).

Usage::

    nice -n 5 python benchmarks/batch.py [--frames 6000] [--captures 4] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PATHS = ("pan", "zigzag", "shake", "pan")


def corner_rmse(a: np.ndarray, b: np.ndarray, width: int, height: int) -> float:
    """RMSE (pixels) of the frame corners mapped by two (T, 3, 3) homography stacks."""
    from photonpano import geometry

    c = geometry.corners(width, height)
    return float(np.sqrt(np.mean(np.sum((geometry.apply(a, c) - geometry.apply(b, c)) ** 2, axis=-1))))


def children_cpu_s() -> float:
    """User + system CPU seconds of the finished child processes so far (workers included once joined)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6000)
    parser.add_argument("--captures", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    cli = str(Path(sys.executable).parent / "photonpano")
    load_before = f"{os.getloadavg()[0]:.1f}"
    with tempfile.TemporaryDirectory(prefix="photonpano-batch-") as scratch:
        root = Path(scratch)
        specs = []
        for i in range(args.captures):
            spec = root / f"capture{i}.yaml"
            spec.write_text(f"source: {{plugin: simulate, frames: {args.frames}, seed: {i}, "
                            f"path: {PATHS[i % len(PATHS)]}}}\noutputs: {{trajectory_plot: false}}\n")
            specs.append(spec)
        t0, c0 = time.perf_counter(), children_cpu_s()
        for spec in specs:
            subprocess.run([cli, "-q", "run", str(spec), "-o", str(root / "serial" / spec.stem), "--set",
                            "executor=serial"], check=True, stdout=subprocess.DEVNULL)
        serial_s, serial_cpu = time.perf_counter() - t0, children_cpu_s() - c0
        t0, c0 = time.perf_counter(), children_cpu_s()
        subprocess.run([cli, "-q", "batch", *map(str, specs), "-o", str(root / "batch"), "--set", "executor=dask",
                        "--set", f"workers={args.workers}"], check=True, stdout=subprocess.DEVNULL)
        batch_s, batch_cpu = time.perf_counter() - t0, children_cpu_s() - c0
        from photonpano.api import load

        rmse = []
        for spec in specs:
            serial, batch = load(root / "serial" / spec.stem), load(root / "batch" / spec.stem)
            src = serial.summary["source"]
            rmse.append(corner_rmse(batch.homographies, serial.homographies, src["width"], src["height"]))
    ratio = batch_s / serial_s
    print(f"{args.captures} captures of {args.frames} frames")
    print(f"load average before: {load_before}, after: {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores)")
    print(f"serial, one after another: {serial_s:.1f} s (CPU {serial_cpu:.1f} s)")
    print(f"batch, {args.workers}-worker local Dask cluster: {batch_s:.1f} s (CPU {batch_cpu:.1f} s)")
    print(f"ratio: {ratio:.2f} (acceptance <= 0.6: {'pass' if ratio <= 0.6 else 'FAIL'})")
    for spec, r in zip(specs, rmse):
        print(f"{spec.stem}: corner RMSE vs serial {r:.2e} px ({'pass' if r <= 0.05 else 'FAIL'})")
    return 0 if ratio <= 0.6 and max(rmse) <= 0.05 else 1


if __name__ == "__main__":
    sys.exit(main())
