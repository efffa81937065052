"""Every installed locator on the real registration pair of tests/data (known warp, scale ~1.9).

Prints, per locator and per setting, the mean and largest corner error against the true
homography (tests/data/SOURCES.md), the match and inlier counts and the time. Feature
locators start from the identity; direct locators (``opencv-ecc``, ``kornia-direct``)
from the true warp with its corners moved by 1.6-2.6 px (2.2 px mean), their use in the
pipeline.

Usage::

    python benchmarks/real_pair.py                       # default settings of every locator
    python benchmarks/real_pair.py opencv-sift:refine=lm pycolmap-sift:refine=none
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml
from photonpano import geometry
from photonpano.host import PluginHost
from photonpano.stages import MergedFrames

DATA = Path(__file__).parents[1] / "tests" / "data"
TRUTH = np.array([[1.9068071, 0.09958228, -171.64162],
                  [0.3666181, 1.5628628, -92.86306],
                  [0.0013926513, 0.00030605582, 1.0]])
DIRECT = ("opencv-ecc", "kornia-direct")


def main() -> None:
    """Print one Markdown table row per locator setting."""
    source, target = cv2.imread(str(DATA / "source.png")), cv2.imread(str(DATA / "target.png"))
    gray = np.stack([cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (source, target)])
    masks = np.ones(gray.shape, bool)
    masks[1] = ~np.all(target == (0, 0, 128), axis=-1)
    merged = MergedFrames(flux=gray.astype(np.float32), frames=np.ones(gray.shape, np.float32), images=gray,
                          masks=masks)
    c = geometry.corners(640, 480)
    moved = geometry.apply(TRUTH, c) + np.array([(2.1, -1.4), (-1.7, 2.3), (1.2, 1.9), (-2.4, -0.9)])
    start = cv2.getPerspectiveTransform(c.astype(np.float32), moved.astype(np.float32))
    host = PluginHost()
    registry = host.registry("locator")
    items = sys.argv[1:] or sorted(registry)
    print("| locator | setting | mean corner error (px) | max (px) | matches | inliers | time (s) |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for item in items:
        key, *options = item.split(":")
        opts = {k: yaml.safe_load(v) for k, _, v in (o.partition("=") for o in options)}
        if registry[key].missing_requirements():
            print(f"| `{key}` | {registry[key].install_hint} | | | | | |")
            continue
        locator = registry[key](**opts).build()
        t0 = time.perf_counter()
        initial = (start if key in DIRECT else np.eye(3))[None]
        result = locator.register_pairs(merged, np.array([[0, 1]]), initial)
        seconds = time.perf_counter() - t0
        err = np.linalg.norm(geometry.apply(result.homographies[0], c) - geometry.apply(TRUTH, c), axis=-1)
        setting = ", ".join(options) or "defaults"
        print(f"| `{key}` | {setting} | {err.mean():.3f} | {err.max():.3f} | {result.matches[0]} | "
              f"{result.inliers[0]} | {seconds:.2f} |" + ("" if result.ok[0] else " (flagged failed)"),
              flush=True)


if __name__ == "__main__":
    main()
