"""``photonpano batch`` on a local Dask cluster against the same runs one after another (issue 15).

Four captures (different seeds and camera paths, 6 000 binary frames of the default
254x496 each, simulated from the bundled photograph and written as ``.npy`` photon cubes
before the clock starts, as a lab's recorded captures would be) are reconstructed twice
with the ``pano`` settings:

- ``serial``: four ``photonpano pano CAPTURE --set executor=serial`` processes, one after
  another;
- ``batch``: one ``photonpano batch CAPTURE... --set executor=dask --set workers=2``, a
  local cluster of 2 worker processes, each capture one Dask task (cluster start-up
  included in the time).

With ``--simulate-in-run`` each run simulates its capture itself instead (a ``simulate``
spec per capture, the setting of sessions 5-6): the simulator draws binary frames on all
cores, so the "serial" runs are then partly parallel themselves and the ratio measures
less of what the batch adds.

Prints both wall-clock times (and the CPU time of the processes, which a shared machine
does not change much: the load average is printed too), their ratio (acceptance: <= 0.6) and, per capture, the RMSE
of the frame corners between the batch's and the serial run's homographies (acceptance:
<= 0.05 px; the same serial pipeline runs inside each task, so 0 is expected).

Usage::

    nice -n 5 python benchmarks/batch.py [--frames 6000] [--captures 4] [--workers 2] [--simulate-in-run]
"""

from __future__ import annotations

import argparse
import json
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


def capture(root: Path, i: int, frames: int, in_run: bool) -> Path:
    """Write capture ``i`` under ``root``: a simulate spec, or (default) its simulated .npy photon cube."""
    source = {"plugin": "simulate", "frames": frames, "seed": i, "path": PATHS[i % len(PATHS)]}
    if in_run:
        spec = root / f"capture{i}.yaml"
        spec.write_text(json.dumps({"source": source}))  # JSON is YAML
        return spec
    from photonpano.plugins.sources.simulate import SimulateConfig

    cube = root / f"capture{i}.npy"
    SimulateConfig(**{k: v for k, v in source.items() if k != "plugin"}, cube_path=cube).build()
    return cube


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6000)
    parser.add_argument("--captures", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--simulate-in-run", action="store_true",
                        help="each run simulates its capture (a simulate spec) instead of reading a .npy cube")
    args = parser.parse_args()
    cli = str(Path(sys.executable).parent / "photonpano")
    load_before = f"{os.getloadavg()[0]:.1f}"
    with tempfile.TemporaryDirectory(prefix="photonpano-batch-") as scratch:
        root = Path(scratch)
        inputs = [capture(root, i, args.frames, args.simulate_in_run) for i in range(args.captures)]
        no_plot = ["--set", "outputs.trajectory_plot=false", "--set", "outputs.report=false"]
        t0, c0 = time.perf_counter(), children_cpu_s()
        for path in inputs:
            command = "run" if path.suffix == ".yaml" else "pano"
            subprocess.run([cli, "-q", command, str(path), "-o", str(root / "serial" / path.stem), "--set",
                            "executor=serial", *no_plot], check=True, stdout=subprocess.DEVNULL)
        serial_s, serial_cpu = time.perf_counter() - t0, children_cpu_s() - c0
        t0, c0 = time.perf_counter(), children_cpu_s()
        subprocess.run([cli, "-q", "batch", *map(str, inputs), "-o", str(root / "batch"), "--set", "executor=dask",
                        "--set", f"workers={args.workers}", *no_plot], check=True, stdout=subprocess.DEVNULL)
        batch_s, batch_cpu = time.perf_counter() - t0, children_cpu_s() - c0
        from photonpano.api import load

        rmse = []
        for path in inputs:
            serial, batch = load(root / "serial" / path.stem), load(root / "batch" / path.stem)
            src = serial.summary["source"]
            rmse.append(corner_rmse(batch.homographies, serial.homographies, src["width"], src["height"]))
    ratio = batch_s / serial_s
    where = "simulated in each run" if args.simulate_in_run else "read from .npy photon cubes"
    print(f"{args.captures} captures of {args.frames} frames, {where}")
    print(f"load average before: {load_before}, after: {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores)")
    print(f"serial, one after another: {serial_s:.1f} s (CPU {serial_cpu:.1f} s)")
    print(f"batch, {args.workers}-worker local Dask cluster: {batch_s:.1f} s (CPU {batch_cpu:.1f} s)")
    print(f"ratio: {ratio:.2f} (acceptance <= 0.6: {'pass' if ratio <= 0.6 else 'FAIL'})")
    for path, r in zip(inputs, rmse):
        print(f"{path.stem}: corner RMSE vs serial {r:.2e} px ({'pass' if r <= 0.05 else 'FAIL'})")
    return 0 if ratio <= 0.6 and max(rmse) <= 0.05 else 1


if __name__ == "__main__":
    sys.exit(main())
