"""Cases shared by the locator tests: the real registration pair, the backends, guards.

Imported as ``from locator_cases import ...`` (a unique module name: ``from conftest
import`` would pick whichever conftest was imported first).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).parents[2] / "data"

# target.png = source.png warped by H, which maps target pixels to source pixels (tests/data/SOURCES.md)
H_TARGET_TO_SOURCE = np.array([[1.9068071, 0.09958228, -171.64162],
                               [0.3666181, 1.5628628, -92.86306],
                               [0.0013926513, 0.00030605582, 1.0]])

FEATURE_LOCATORS = ["opencv-sift", "opencv-orb", "kornia-sift", "pycolmap-sift"]
DIRECT_LOCATORS = ["opencv-ecc", "kornia-direct"]
ALL_LOCATORS = FEATURE_LOCATORS + DIRECT_LOCATORS

OPTIONAL_MODULES = {"kornia-sift": "kornia", "kornia-direct": "kornia", "pycolmap-sift": "pycolmap"}


def need_backend(key: str) -> None:
    """Skip (guard only: the test extra installs every backend) if ``key``'s extra is missing."""
    module = OPTIONAL_MODULES.get(key)
    if module:
        pytest.importorskip(module)
    if module == "kornia":
        import torch

        torch.set_num_threads(1)


def perturbed_truth(shifts_px=((2.1, -1.4), (-1.7, 2.3), (1.2, 1.9), (-2.4, -0.9))) -> np.ndarray:
    """The true warp with the target's corners moved by a few pixels (a direct method's start)."""
    import cv2
    from photonpano import geometry

    c = geometry.corners(640, 480).astype(np.float32)
    moved = geometry.apply(H_TARGET_TO_SOURCE, c) + np.array(shifts_px)
    h = cv2.getPerspectiveTransform(c, moved.astype(np.float32))
    return h / h[2, 2]
