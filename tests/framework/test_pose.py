"""photonpano.pose: SE(3) interpolation, similarity alignment, trajectory metrics, plane homographies."""

import json

import numpy as np
import pytest
from photonpano.errors import SpecError
from photonpano.pose import (
    Intrinsics,
    absolute_trajectory_error,
    interpolate_poses,
    plane_homographies,
    relative_pose_error,
    umeyama,
)
from scipy.spatial.transform import Rotation


def _path(n, seed=0):
    """A smooth 6-DoF path: poses (n, 4, 4), rotation and centre smooth in the frame index."""
    t = np.arange(n) / n
    rot = Rotation.from_rotvec(np.stack([0.02 * np.sin(3 * t), 0.1 * t, 0.01 * np.cos(2 * t)], 1))
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = rot.as_matrix()
    poses[:, :3, 3] = np.stack([0.3 * t, 0.02 * np.sin(5 * t), 0.05 * t**2], 1)
    poses[:, 3, 3] = 1
    return poses


def _similarity(poses, s, rot, t):
    out = poses.copy()
    out[:, :3, :3] = rot @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ rot.T + t
    return out


def test_interpolation_passes_through_keyframes_and_follows_a_smooth_path():
    truth = _path(2000)
    keys = np.arange(100, 2000, 200)
    est = interpolate_poses(keys, truth[keys], 2000)
    np.testing.assert_allclose(est[keys], truth[keys], atol=1e-9)
    # between keyframes within 0.05 mm, extrapolated 100 frames at each end within
    # 0.5 mm; rotations within 0.02 degrees
    error = np.abs(est[:, :3, 3] - truth[:, :3, 3]).max(1)
    assert error[100:1901].max() < 5e-5 and error.max() < 5e-4
    angle = Rotation.from_matrix(np.swapaxes(est[:, :3, :3], 1, 2) @ truth[:, :3, :3]).magnitude()
    assert np.degrees(angle.max()) < 0.02


def test_interpolation_skips_missing_poses_and_handles_degenerate_inputs():
    truth = _path(1000)
    keys = np.arange(50, 1000, 100)
    poses = truth[keys].copy()
    poses[3] = np.nan
    est = interpolate_poses(keys, poses, 1000)
    assert np.isfinite(est).all() and np.abs(est[:, :3, 3] - truth[:, :3, 3]).max() < 1e-3
    assert np.isnan(interpolate_poses(keys[:0], poses[:0], 10)).all()
    np.testing.assert_allclose(
        interpolate_poses(keys[:1], truth[keys[:1]], 5), np.repeat(truth[keys[:1]], 5, 0)
    )


def test_umeyama_recovers_a_similarity_and_ate_ignores_it():
    truth = _path(500)
    rot = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    moved = _similarity(truth, 2.5, rot, np.array([1.0, -2.0, 0.5]))
    s, r, t = umeyama(truth[:, :3, 3], moved[:, :3, 3])
    assert abs(s - 2.5) < 1e-9 and np.allclose(r, rot) and np.allclose(t, [1.0, -2.0, 0.5])
    # an estimate that differs from the truth only by a similarity has no error
    assert absolute_trajectory_error(moved, truth) < 1e-9
    assert relative_pose_error(moved, truth, 100)["translation_m"] < 1e-9


def test_rpe_measures_a_known_vibration_as_a_share_of_the_motion():
    truth = _path(3000)
    est = truth.copy()
    wobble = 1e-3 * np.sin(2 * np.pi * np.arange(3000) / 300)  # 1 mm along y, period 300 frames
    est[:, 1, 3] += wobble
    rpe = relative_pose_error(est, truth, 150, stride=1)
    # over half a period the wobble changes by 2 mm (RMS 2 mm * 0.707 over all phases)
    assert rpe["translation_m"] == pytest.approx(2e-3 / np.sqrt(2), rel=0.1)
    assert rpe["percent"] == pytest.approx(100 * rpe["translation_m"] / rpe["motion_m"])
    assert absolute_trajectory_error(est, truth) < 1e-3


def test_plane_homographies_map_plane_points_between_views():
    k = Intrinsics(300.0, 310.0, 99.5, 59.5).matrix()
    poses = _path(50)
    reference = poses[25]
    normal, distance = np.array([0.0, 0.0, 1.0]), 2.5
    h = plane_homographies(poses, k, reference, normal, distance)
    # points on the plane z = 2.5 of the reference camera, seen by frame 3 and by the reference
    rng = np.random.default_rng(0)
    cam_ref = np.c_[rng.uniform(-1, 1, (20, 2)), np.full(20, distance)]
    world = cam_ref @ reference[:3, :3].T + reference[:3, 3]
    cam_3 = (world - poses[3, :3, 3]) @ poses[3, :3, :3]
    x3 = cam_3 @ k.T
    x3 /= x3[:, 2:]
    xr = cam_ref @ k.T
    xr /= xr[:, 2:]
    mapped = x3 @ h[3].T
    np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], xr[:, :2], atol=1e-6)
    np.testing.assert_allclose(h[25], np.eye(3), atol=1e-9)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not valid JSON"),
        ('{"fx": 400, "fy": 400, "cx": 10}', "'cy'"),
        ('{"fx": -1, "fy": 400, "cx": 10, "cy": 5}', "positive"),
        ("[1, 2]", "JSON object"),
    ],
)
def test_bad_intrinsics_files_are_one_line_spec_errors(tmp_path, content, message):
    path = tmp_path / "k.json"
    path.write_text(content)
    with pytest.raises(SpecError, match=message) as info:
        Intrinsics.load(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(SpecError, match="cannot read"):
        Intrinsics.load(tmp_path / "missing.json")


def test_intrinsics_round_trip_and_colmap_half_pixel():
    k = Intrinsics(400.0, 401.0, 247.5, 126.5)
    assert Intrinsics(**json.loads(json.dumps(k.as_dict()))) == k
    assert k.colmap_params() == [400.0, 401.0, 248.0, 127.0]
