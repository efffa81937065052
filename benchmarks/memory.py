"""Peak resident memory against capture length (issue 4's memory acceptance).

Writes bit-packed 254x496 photon cubes of growing length to a scratch folder (a 20 000
frame simulation of the bundled photo, tiled forward-backward so the motion stays
continuous), then measures, each in a fresh subprocess, the peak resident set size
(``VmHWM`` of ``/proc/self/status``, which counts touched pages of memory-mapped files too;
``ru_maxrss`` is not used because Linux carries it over from the parent across ``exec``):

- ``stream``: the source alone, every frame counted once in panorama-sized chunks
  (``sum_ranges`` over 128 sub-batches of 12 frames per call) and then the whole
  panorama assembly (``assemble_panorama`` along a pan back and forth over 300 px at
  0.01 px per frame, so the canvas does not grow with the capture);
- ``pipeline``: the full reconstruction (``photonpano.pipeline.reconstruct``) with the
  given levels and pair offsets.

Usage::

    python benchmarks/memory.py --frames 200000 400000 --modes stream
    python benchmarks/memory.py --frames 50000 100000 --modes pipeline --levels 2

Results are printed as a table and appended to ``--json`` if given. Cubes are kept in
``--scratch`` (default ``/tmp/photonpano-memory``) for reuse; delete them afterwards
(200 000 frames take 3.1 GB).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

FRAME_BYTES = 254 * 62


def write_cube(path: Path, frames: int, base: Path) -> None:
    """Write a (frames, 254, 62) uint8 cube by tiling the base simulation forward and backward."""
    if path.exists():
        return
    src = np.load(base, mmap_mode="r")
    n = len(src)
    part = path.with_suffix(".part")
    with open(part, "wb") as f:
        np.lib.format.write_array_header_2_0(f, {"descr": "|u1", "fortran_order": False,
                                                 "shape": (frames, 254, 62)})
        done, forward = 0, True
        while done < frames:
            k = min(n, frames - done)
            for a in range(0, k, 2000):  # 2 000 frames (31 MB) at a time
                idx = np.arange(a, min(a + 2000, k))
                f.write(np.ascontiguousarray(src[idx if forward else n - 1 - idx]).tobytes())
            done, forward = done + k, not forward
    part.rename(path)


CHILD = r"""
import json, resource, sys, time
import numpy as np
from pathlib import Path
mode, cube, levels, offsets = sys.argv[1], sys.argv[2], int(sys.argv[3]), json.loads(sys.argv[4])
t0 = time.perf_counter()
from photonpano.host import PluginHost
from photonpano.spec import validate_spec
spec = validate_spec({"source": {"plugin": "npy-cube", "path": cube}, "levels": levels,
                      "pair_offsets": offsets}, PluginHost())
source = spec.source.build()
def hwm_kb():
    # VmHWM: peak RSS of this process image (ru_maxrss would carry the parent's peak across exec)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
base = hwm_kb()
if mode == "stream":
    from photonpano.compose import assemble_panorama
    step = 12 * 128
    total = 0
    for start in range(0, source.n_frames, step):
        stop = min(start + step, source.n_frames)
        edges = np.unique(np.r_[np.arange(start, stop, 12), stop])
        total += int(source.sum_ranges(edges).sum(dtype=np.int64))
    t = np.arange(source.n_frames)
    x = 300.0 * np.abs((t / 30000.0) % 2 - 1)  # back and forth over 300 px at 0.01 px per frame
    pan = np.repeat(np.eye(3)[None], source.n_frames, axis=0)
    pan[:, 0, 2] = x
    pano = assemble_panorama(source, pan)
else:
    from photonpano.pipeline import reconstruct
    reconstruct(spec, source)
peak = hwm_kb()
print(json.dumps({"peak_mb": peak / 1024, "after_imports_mb": base / 1024,
                  "seconds": time.perf_counter() - t0}))
"""


def measure(mode: str, cube: Path, levels: int, offsets: list[int]) -> dict:
    """Run one measurement in a fresh interpreter; return its JSON report."""
    out = subprocess.run([sys.executable, "-c", CHILD, mode, str(cube), str(levels), json.dumps(offsets)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Parse arguments, write the cubes and print peak memory per length and mode."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[200_000, 400_000])
    parser.add_argument("--modes", nargs="+", default=["stream", "pipeline"], choices=["stream", "pipeline"])
    parser.add_argument("--levels", type=int, default=3)
    parser.add_argument("--pair-offsets", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64])
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/photonpano-memory"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    args.scratch.mkdir(parents=True, exist_ok=True)
    base = args.scratch / "base_20000.npy"
    if not base.exists():
        from photonpano.plugins.sources.simulate import SimulateConfig

        t0 = time.perf_counter()
        SimulateConfig(frames=20_000, cube_path=base.with_suffix(".part.npy")).build()
        base.with_suffix(".part.npy").rename(base)
        print(f"simulated the base cube in {time.perf_counter() - t0:.0f} s", flush=True)
    rows = []
    for frames in args.frames:
        cube = args.scratch / f"cube_{frames}.npy"
        write_cube(cube, frames, base)
        for mode in args.modes:
            report = measure(mode, cube, args.levels, args.pair_offsets)
            row = {"frames": frames, "mode": mode, "cube_gb": cube.stat().st_size / 1e9, **report}
            rows.append(row)
            print(f"{frames:>8} frames ({row['cube_gb']:.2f} GB) {mode:<8}: peak RSS {report['peak_mb']:7.0f} MB "
                  f"(after imports {report['after_imports_mb']:.0f} MB), {report['seconds']:.0f} s", flush=True)
    for mode in args.modes:
        peaks = [r["peak_mb"] for r in rows if r["mode"] == mode]
        if len(peaks) > 1:
            print(f"{mode}: peak grows {100 * (peaks[-1] / peaks[0] - 1):+.1f} % from {args.frames[0]} to "
                  f"{args.frames[-1]} frames")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
