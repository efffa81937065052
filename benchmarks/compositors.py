"""Micro-benchmark of the panorama kernels: milliseconds per sub-batch of count images.

Feeds the same synthetic sub-batch (128 count images of 254x496, translations only)
to drizzle's square and point drops (numba, one thread) and to OpenCV's bilinear
``warpPerspective`` (the ``flux-canvas`` compositor's warp), and prints the CPU time
per count image (process CPU time, the best of three calls: on a shared machine wall
time measures the other jobs). The whole-pipeline figure is
``benchmarks/performance.py``'s panorama line.

Usage::

    python benchmarks/compositors.py
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from photonpano.plugins.compositors._splat import splat_point, splat_square


def per_image_ms(run, images: int) -> float:
    """Best CPU time of three ``run()`` calls divided by ``images``, in milliseconds (after a warm-up call)."""
    run()
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        run()
        best = min(best, time.process_time() - t0)
    return best / images * 1e3


def main(batch: int = 128, height: int = 254, width: int = 496) -> None:
    """Print the time per count image of each kernel."""
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    counts = rng.integers(0, 60, (batch, height, width)).astype(np.uint16)
    n_frames = np.full(batch, 50, np.int64)
    homographies = np.repeat(np.eye(3)[None], batch, axis=0)
    homographies[:, 0, 2] = np.linspace(10, 40, batch) + 0.3
    homographies[:, 1, 2] = 12.7
    weights = np.ones((height, width), np.float32)
    canvas = (height + 50, width + 110)
    acc = np.zeros((*canvas, 2), np.float32)
    flux = counts.astype(np.float32)

    def bilinear() -> None:
        for b in range(batch):
            cv2.warpPerspective(flux[b], homographies[b], canvas[::-1], flags=cv2.INTER_LINEAR)

    def square() -> None:
        splat_square(counts, n_frames, homographies, weights, acc, 1.0)

    def point() -> None:
        splat_point(counts, n_frames, homographies, weights, acc)

    for name, run in (("drizzle square drop", square), ("drizzle point drop", point), ("bilinear warp", bilinear)):
        print(f"{name:<20} {per_image_ms(run, batch):.2f} ms")


if __name__ == "__main__":
    main()
