"""A camera turning about its centre: the level's pose graph as one focal length and a rotation per keyframe."""

import numpy as np
import pytest
from photonpano import geometry
from photonpano.metrics import trajectory_error
from photonpano.posegraph import chain_keyframes, pairs_at_offsets, refine_keyframes
from photonpano.records import PairRegistrations
from photonpano.turning_camera import TURNING_DISAGREEMENT_RATIO, fit_turning_camera, turning_keyframes

W, H, FOCAL = 248, 127, 210.0
"""A level-1 frame binned 2x2 from 496 x 254, and the suite's tripod focal length (420 px) binned."""


def turning_camera(yaw_deg, pitch_deg, focal=FOCAL):
    """(G, 3, 3) frame-to-scene homographies ``T_c K R K^-1 T_c^-1`` of a camera yawing then pitching."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_euler("YX", np.stack([yaw_deg, pitch_deg], axis=1), degrees=True).as_matrix()
    k = np.diag([focal, focal, 1.0])
    return geometry.normalize(geometry.from_centre(k @ rotation @ np.linalg.inv(k), W, H))


def measured_pairs(truth, offsets, keystone_noise_px, shift_noise_px, seed):
    """Pair registrations of ``truth`` at ``offsets``: each pair's keystone and shift measured with noise.

    As rescues on binned frames of little texture measure them (docs/accuracy.md: their
    keystones 1-4 px off at the frame's corner, their shifts a few tenths of a pixel).
    """
    rng = np.random.default_rng(seed)
    index = pairs_at_offsets(len(truth), offsets)
    exact = np.linalg.inv(truth[index[:, 0]]) @ truth[index[:, 1]]
    noise = np.zeros((len(index), 8))
    noise[:, 4:6] = rng.normal(0, shift_noise_px, (len(index), 2))
    noise[:, 6] = rng.normal(0, keystone_noise_px, len(index)) / ((W - 1) / 2) ** 2
    noise[:, 7] = rng.normal(0, keystone_noise_px, len(index)) / ((H - 1) / 2) ** 2
    error = geometry.from_centre(geometry.homographies_from_params(noise), W, H)
    found = PairRegistrations(exact @ error, np.full(len(index), 100), np.full(len(index), 100.0),
                              np.ones(len(index), bool))
    return index, found


def free_solution(index, found, g):
    """The eight-parameter pose graph's keyframes (chain, then the joint solve), as a pairwise level solves them."""
    chain = found.take(slice(0, g - 1))
    keyframes = chain_keyframes(np.repeat(np.eye(3)[None], g, axis=0), chain)
    return refine_keyframes(keyframes, index, found, W, H)


def test_a_tripod_pan_measured_with_noisy_keystones_is_recovered_as_a_turning_camera():
    """A 50-degree pan at f = 210 px: the free pose graph bends with the pairs' keystone noise; the turn does not.

    The pairs' keystones are 1.5 px off at the corners (random, as rescues on binned
    frames of little texture measure them), their shifts 0.2 px. Chained and solved with
    eight parameters per keyframe, the trajectory follows the keystones' random walk
    (1.8 px over the pan); solved as one focal length and a rotation per keyframe, a
    third of that (0.62 px, the shifts' own random walk), the focal length within 3 %.
    """
    g = 80
    yaw = np.linspace(-25, 25, g)
    pitch = 0.5 * np.sin(np.linspace(0, 6 * np.pi, g))
    truth = turning_camera(yaw, pitch)
    index, found = measured_pairs(truth, (1, 2, 4, 8, 16), 1.5, 0.2, seed=0)
    free = free_solution(index, found, g)
    fit = fit_turning_camera(free, index, found, W, H)
    free_error = trajectory_error(free, truth, W, H).rmse_px
    turned_error = trajectory_error(fit.keyframes, truth, W, H).rmse_px
    assert abs(fit.focal_px / FOCAL - 1) < 0.03, fit
    assert free_error > 1.0, free_error
    assert turned_error < 0.5 * free_error, (turned_error, free_error)


def test_exact_pairs_of_a_turning_camera_are_fitted_exactly():
    """Noise-free pairs: the focal length and every keyframe as the truth's (up to the first keyframe's gauge)."""
    g = 30
    truth = turning_camera(np.linspace(-20, 20, g), np.linspace(-3, 3, g))
    index, found = measured_pairs(truth, (1, 2, 4), 0.0, 0.0, seed=1)
    start = truth @ geometry.homographies_from_params(np.full((g, 8), 1e-4) * [1, 1, 1, 1, 10, 10, 1e-3, 1e-3])
    fit = fit_turning_camera(start, index, found, W, H)
    assert fit.focal_px == pytest.approx(FOCAL, rel=1e-6)
    expected = start[0] @ np.linalg.inv(truth[0]) @ truth  # the first keyframe is held where it started
    assert geometry.mean_corner_distance(fit.keyframes, expected, W, H).max() < 1e-6


def test_a_zooming_camera_keeps_the_free_solution():
    """A camera that zooms by +-5 % is no turning camera: the fit disagrees with the pairs and is not kept.

    The figures say so (``kept`` False, the two disagreements), and the keyframes are the
    free solution's, unchanged.
    """
    g = 40
    zoom = 1 + 0.05 * np.sin(np.linspace(0, 4 * np.pi, g))
    shift = np.linspace(0, 120, g)
    truth = np.stack([geometry.from_centre(np.array([[z, 0, s], [0, z, 0], [0, 0, 1]]), W, H)
                      for z, s in zip(zoom, shift)])
    index, found = measured_pairs(truth, (1, 2, 4), 0.2, 0.05, seed=2)
    free = free_solution(index, found, g)
    keyframes, figures = turning_keyframes(free, index, found, found.ok, W, H)
    assert not figures["kept"], figures
    assert figures["disagreement_px"] > TURNING_DISAGREEMENT_RATIO * figures["free_disagreement_px"]
    assert keyframes is free


def test_a_level_whose_failed_consecutive_pairs_leave_islands_is_bridged():
    """Every other consecutive pair failed and a keyframe pair joined to the rest by nothing else: the fit bridges it.

    As a level's outlier rejection leaves them (the outdoor camera's tripod pan: frames 3
    and 4 joined only to each other). ``turning_keyframes`` bridges the failed consecutive
    pairs with the free solution's steps at a token weight, so the island follows the free
    solution instead of floating; the fit is kept and within 0.5 px of the truth.
    """
    g = 40
    truth = turning_camera(np.linspace(-15, 15, g), np.zeros(g))
    index, found = measured_pairs(truth, (1, 2, 4, 8), 0.5, 0.05, seed=3)
    free = free_solution(index, found, g)
    island = np.zeros(len(index), bool)
    island[[2, 4]] = True  # consecutive pairs (2, 3) and (4, 5) fail
    island |= (np.isin(index, [3, 4]).any(axis=1)) & (index[:, 1] - index[:, 0] > 1)  # and every longer one of 3, 4
    found = found.with_ok(found.ok & ~island)
    keyframes, figures = turning_keyframes(free, index, found, found.ok, W, H)
    assert figures["kept"], figures
    assert trajectory_error(keyframes, truth, W, H).rmse_px < 0.5
