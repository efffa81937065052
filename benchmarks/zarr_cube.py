"""Size and read speed of a photon cube as ``.npy`` against zarr (issue 15).

Simulates a bit-packed capture of the bundled photo (``--frames`` binary frames of
254x496, flux ``--flux``), converts it with ``photonpano convert`` (Zstandard level 1,
time chunks of about 4 MiB), and reports:

- the size on disk of each (``du``-style: allocated blocks);
- the time of ``convert`` .npy -> .zarr;
- the read speed of ``sum_ranges`` over the whole capture in groups of ``--group``
  frames (what the merge of level 1 reads), through ``npy-cube`` and ``zarr-cube``,
  best of 3, with the files in the page cache (a warm read; a cold read from disk or
  network is bounded by the storage, where zarr reads fewer bytes).

Usage::

    nice -n 5 python benchmarks/zarr_cube.py [--frames 20000] [--flux 0.5] [--group 250]
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


def disk_bytes(path: Path) -> int:
    """Allocated bytes of a file or of every file under a folder."""
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(os.stat(p).st_blocks * 512 for p in files)


def read_speed(source, group: int, repeats: int = 3) -> float:
    """Best wall-clock seconds of ``sum_ranges`` over the whole capture in groups of ``group`` frames."""
    edges = np.arange(0, source.n_frames + 1, group, dtype=np.int64)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        source.sum_ranges(edges)
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--flux", type=float, default=0.5)
    parser.add_argument("--group", type=int, default=250)
    args = parser.parse_args()
    from photonpano.plugins.sources.npy_cube import NpyCubeConfig
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.plugins.sources.zarr_cube import ZarrCubeConfig

    with tempfile.TemporaryDirectory(prefix="photonpano-zarr-") as scratch:
        npy, zr = Path(scratch) / "cube.npy", Path(scratch) / "cube.zarr"
        SimulateConfig(frames=args.frames, flux=args.flux, cube_path=npy).build()
        t0 = time.perf_counter()
        subprocess.run([str(Path(sys.executable).parent / "photonpano"), "convert", str(npy), "-o", str(zr)],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        convert_s = time.perf_counter() - t0
        sources = {"npy-cube": NpyCubeConfig(path=npy).build(), "zarr-cube": ZarrCubeConfig(path=zr).build()}
        edges = np.arange(0, args.frames + 1, args.group, dtype=np.int64)
        np.testing.assert_array_equal(sources["npy-cube"].sum_ranges(edges), sources["zarr-cube"].sum_ranges(edges))
        mean_p = float(sources["npy-cube"].sum_ranges(np.array([0, args.frames])).mean() / args.frames)
        print(f"{args.frames} frames of 254x496, flux {args.flux} (mean P(1) = {mean_p:.3f}), "
              f"groups of {args.group} frames")
        print(f"convert .npy -> .zarr: {convert_s:.1f} s")
        print("| container | size on disk (MB) | ratio | sum_ranges, warm (s) | frames/s |")
        print("| --- | --- | --- | --- | --- |")
        base = disk_bytes(npy)
        for name, path in (("npy-cube", npy), ("zarr-cube", zr)):
            seconds = read_speed(sources[name], args.group)
            size = disk_bytes(path)
            print(f"| {name} | {size / 1e6:.1f} | {size / base:.2f} | {seconds:.2f} | {args.frames / seconds:,.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
