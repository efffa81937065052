"""Executor independence (issue 29): one capture on every executor, homographies compared.

Runs the default spec on a simulated capture (254x496 frames, the bundled photo; or an
``.npy`` cube with ``--cube``) with ``serial``, ``threads`` (1 and 2 workers) and
``dask`` (2 workers, a local cluster) and prints, per executor, the wall time of the
levels and of the panorama and the worst frame's mean corner distance (px) to the
serial run. Measured on 2 cores, 20 000 frames, before (c134b78) and after:

==========  =============  ===================
executor    before (px)    after (px)
==========  =============  ===================
threads 1   2.3e-13        2.1e-13
threads 2   6.6e-4         2.1e-13
dask 2      0.0255         0
==========  =============  ===================

Timings on the same 20 000 frames as an ``.npy`` cube, 2 shared cores (noisy: +-30 %),
before -> after: ``threads`` 2 levels 2.9 -> 2.8 s, panorama 0.73 -> 0.63 s; ``dask`` 2
levels 9.5 -> 10.6 s, panorama 5.5 -> 6.2 s (8 fixed runs of chunks shipped instead of
one per worker). On the in-memory simulation ``dask`` pays more (each run ships the
photons: panorama 14 -> 18-25 s); ``dask`` is for captures on shared storage.

Usage::

    python benchmarks/executors.py --frames 20000
    python benchmarks/executors.py --cube capture.npy
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

EXECUTORS = [("serial", 1), ("threads", 1), ("threads", 2), ("dask", 2)]
"""(executor, workers) compared, the first the reference."""


def worst_corner_distance(homographies: np.ndarray, reference: np.ndarray, width: int, height: int) -> float:
    """Max over frames of the mean distance (px) between the frame corners mapped by two (T, 3, 3) sets."""
    from photonpano import geometry

    corners = geometry.corners(width, height)
    distance = np.linalg.norm(geometry.apply(homographies, corners) - geometry.apply(reference, corners), axis=-1)
    return float(distance.mean(axis=-1).max())


def main() -> None:
    """Run the capture on each executor and print the table (see the module)."""
    import photonpano

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="simulated binary frames")
    parser.add_argument("--cube", type=Path, help="an .npy photon cube instead of the simulation")
    args = parser.parse_args()
    source = ({"plugin": "npy-cube", "path": str(args.cube)} if args.cube else
              {"plugin": "simulate", "frames": args.frames})
    spec = {"source": source, "outputs": {"trajectory_plot": False, "report": False}}
    rows, reference = [], None
    with tempfile.TemporaryDirectory(prefix="photonpano-executors-") as tmp:
        for executor, workers in EXECUTORS:
            out = Path(tmp) / f"{executor}{workers}"
            result = photonpano.run({**spec, "executor": executor, "workers": workers}, out, progress=False)
            homographies = result.homographies
            height, width = result.summary["source"]["height"], result.summary["source"]["width"]
            if reference is None:
                reference = homographies
            timings = result.summary["timings_s"]
            rows.append((f"{executor} {workers}", timings["levels"], timings["panorama"],
                         worst_corner_distance(homographies, reference, width, height)))
    print(f"{'executor':<10} {'levels (s)':>10} {'panorama (s)':>12} {'vs serial (px)':>15}")
    for name, levels, panorama, distance in rows:
        print(f"{name:<10} {levels:>10.2f} {panorama:>12.2f} {distance:>15.3g}")


if __name__ == "__main__":  # the Dask workers import this module: run only when executed
    main()
