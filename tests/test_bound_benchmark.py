"""benchmarks/bound.py: the Cramer-Rao bound of a frame's homography from its photons."""

import numpy as np
import pytest
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


def _path(offsets_x: np.ndarray) -> np.ndarray:
    """(T, 3, 3) translations of a frame inside :func:`_scene` (x offsets per frame, y 70 px)."""
    path = np.repeat(np.eye(3)[None], len(offsets_x), axis=0)
    path[:, 0, 2], path[:, 1, 2] = offsets_x, 70.0
    return path


def test_the_trajectory_bound_pools_the_frames_of_each_knot_and_ignores_one_homography():
    """Four times the frames per knot: half the bound; a still camera's constant error: one homography, not counted."""
    bound = _module()
    scene = _scene(2.0)
    information = bound.frame_information(scene, _path(np.array([100.0]))[0], [0.5])  # (1, 8, 8)
    shift_only = [None, None, 1.0, None, None, 1.0, None, None]

    def still(n: int, spacing: float) -> tuple[float, float]:
        spacings = [spacing * s if s else None for s in shift_only]
        return bound.trajectory_bound(information, np.array([0]), _path(np.full(n, 100.0)), spacings)

    short, long = still(2000, 500), still(8000, 2000)  # the same knots, 4x the frames behind each
    assert long[0] == pytest.approx(short[0] / 2, rel=5e-3)  # (the frames sample the knots a little differently)
    assert short[1] < 1e-9 and long[1] < 1e-9
    constant, _ = bound.trajectory_bound(information, np.array([0]), _path(np.full(2000, 100.0)), [None] * 8)
    assert constant < 1e-6 * short[0]


def test_finer_knots_cost_precision_and_coarser_ones_miss_the_vibration():
    """Knots closer together pool fewer frames each; too far apart, the splines cannot follow a vibration."""
    bound = _module()
    scene, n = _scene(2.0), 4000
    t = np.arange(n)
    path = _path(100.0 + 5.0 * np.sin(2 * np.pi * t / 1000))  # a 5 px vibration, 1 000 frames a period
    information = bound.frame_information(scene, path[0], [0.5])
    sampled = np.array([0])

    def at(shift: float, rest: float | None) -> tuple[float, float]:
        return bound.trajectory_bound(information, sampled, path, [rest, rest, shift, rest, rest, shift, rest, rest])

    fine, coarse = at(100, None), at(400, None)
    assert fine[0] > coarse[0]  # fewer frames per shift knot: more noise
    assert coarse[1] > 10 * fine[1]  # a cubic spline's model error grows as the spacing to the 4th
    assert at(100, 500)[0] > fine[0]  # six more parameters to estimate along the capture: more noise again
    assert bound.trajectory_bound(information, sampled, _path(100.0 + 0.01 * t), [400] * 8)[1] < 1e-6  # a pan


def test_a_frame_turned_with_its_scene_carries_the_same_information():
    """The scene and the frame's homography turned by 90 degrees together: the same information (the chain rule)."""
    bound = _module()
    scene = _scene(2.0)
    at = _path(np.array([100.0]))[0]
    turn = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, scene.shape[1] - 1.0], [0.0, 0.0, 1.0]])  # np.rot90's map
    straight = bound.frame_information(scene, at, [0.5])[0]
    turned = bound.frame_information(np.ascontiguousarray(np.rot90(scene)), turn @ at, [0.5])[0]
    assert np.allclose(turned, straight, rtol=1e-4)
