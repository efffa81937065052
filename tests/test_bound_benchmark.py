"""benchmarks/bound.py: the Cramer-Rao bound of a frame's homography from its photons."""

import numpy as np
from capture_helpers import load_benchmark


def _module():
    return load_benchmark("bound")


def _scene(blur: float) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.random((400, 700), dtype=np.float32), (0, 0), blur)
    return (0.1 + 0.8 * (texture - texture.min()) / (texture.max() - texture.min())).astype(np.float32)


def test_the_bound_falls_with_light_and_sharper_texture():
    """Ten times less light: about sqrt(10) times the bound (Poisson-like at low flux); a blurrier scene: more."""
    bound = _module()
    at = np.array([[1.0, 0.0, 100.0], [0.0, 1.0, 70.0], [0.0, 0.0, 1.0]])  # the frame inside the scene
    sharp = _scene(2.0)
    corner_bright, shift_bright = bound.corner_and_shift_bound(sharp, at, 0.5)
    corner_dim, shift_dim = bound.corner_and_shift_bound(sharp, at, 0.05)
    assert 0 < shift_bright < corner_bright  # the corners also carry rotation, scale and perspective
    assert 2.5 < corner_dim / corner_bright < 3.5  # sqrt(10) = 3.16, less where bright pixels saturate
    assert bound.corner_and_shift_bound(_scene(6.0), at, 0.5)[0] > 2 * corner_bright
