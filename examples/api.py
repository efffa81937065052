"""The Python API in a few lines: simulate a capture, reconstruct it, read the run back.

Run it from anywhere (it writes into a temporary folder)::

    python examples/api.py

It prints the shapes of the homographies and the panorama, the trajectory error against
the simulator's ground truth, and the panorama's size on disk. CI runs it
(tests/test_api.py), so it cannot go stale.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import photonpano


def main(frames: int = 3000) -> photonpano.api.RunResult:
    """Reconstruct a short simulated capture in memory, then once more into a folder."""
    # 1. In memory: a spec as a mapping (YAML text or a file path work too); nothing is written.
    result = photonpano.run({"source": {"plugin": "simulate", "frames": frames}},
                            overrides={"source.flux": 0.5}, progress=False)
    print("homographies", result.homographies.shape, "panorama", result.panorama.shape)
    print(f"trajectory RMSE {result.summary['ground_truth']['trajectory_rmse_px']:.3f} px")

    # 2. Into a folder, then read back with photonpano.load.
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        photonpano.run("source: {plugin: simulate, frames: %d}\nlevels: 2\n" % frames, out_dir=out,
                       progress=False)
        again = photonpano.load(out)
        print("loaded", sorted(p.name for p in out.iterdir()))
        assert np.array_equal(again.homographies.shape, (frames, 3, 3))
    return result


if __name__ == "__main__":
    main()
