"""simulate3d and pycolmap-sfm: ground truth consistency, the pose contract, the ``pose`` command."""

import importlib.util
import json

import numpy as np
import pytest
from photonpano.cli import app
from photonpano.plugins.pose.pycolmap_sfm import PycolmapSfMConfig
from photonpano.plugins.sources.simulate3d import Simulate3DConfig, camera_poses
from photonpano.testing import PoseEstimatorContract, SourceContract
from typer.testing import CliRunner

needs_pycolmap = pytest.mark.skipif(
    importlib.util.find_spec("pycolmap") is None,
    reason="pycolmap is not installed (pip install 'photonpano[colmap]')",
)


class TestSimulate3D(SourceContract):
    config_class = Simulate3DConfig
    entry_point = "simulate3d"
    config_kwargs = {"frames": 200, "height": 64, "width": 120, "focal_px": 100.0}


def test_room_frames_follow_their_true_poses():
    # The mean of 400 binary frames matches the rendered intensity of its centre pose.
    room = Simulate3DConfig(frames=800, height=64, width=120, focal_px=100.0, vibration_mm=0.0).build()
    rate = room.sum_ranges(np.array([200, 600]))[0] / 400
    expected = 1 - np.exp(-room.config.flux * room.render(400))
    assert abs(rate.mean() - expected.mean()) < 0.01
    assert np.corrcoef(rate.ravel(), expected.ravel())[0, 1] > 0.8
    # a frame rendered from another part of the path does not match as well
    far = 1 - np.exp(
        -room.config.flux
        * Simulate3DConfig(frames=800, height=64, width=120, focal_px=100.0, path_m=1.0).build().render(0)
    )
    assert (
        np.corrcoef(rate.ravel(), far.ravel())[0, 1] < np.corrcoef(rate.ravel(), expected.ravel())[0, 1] - 0.1
    )


def test_camera_path_length_and_vibration():
    cfg = Simulate3DConfig(frames=20_000)
    poses = camera_poses(cfg)
    assert poses.shape == (20_000, 4, 4)
    np.testing.assert_allclose(
        poses[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2),
        np.broadcast_to(np.eye(3), (20_000, 3, 3)),
        atol=1e-12,
    )
    travel = np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3])
    assert 0.34 < travel < 0.40
    still = camera_poses(Simulate3DConfig(frames=20_000, vibration_mm=0.0, vibration_deg=0.0))
    wobble = np.linalg.norm(poses[:, :3, 3] - still[:, :3, 3], axis=1)
    assert 2e-3 < wobble.max() <= 3e-3  # 2 mm along x and y, 1 mm along z


@needs_pycolmap
@pytest.mark.slow
class TestPycolmapSfM(PoseEstimatorContract):
    config_class = PycolmapSfMConfig
    entry_point = "pycolmap-sfm"
    config_kwargs = {"group_size": 500, "levels": 2}
    capture_frames = 5000
    max_ate_m = 0.01


def test_pycolmap_sfm_without_pycolmap_is_a_clear_missing_dependency(monkeypatch):
    from photonpano.errors import MissingDependency

    monkeypatch.setattr(PycolmapSfMConfig, "requires", ("a_module_that_is_not_installed",))
    with pytest.raises(MissingDependency, match=r"photonpano\[colmap\]"):
        PycolmapSfMConfig().build()


def _intrinsics_file(tmp_path, **values):
    path = tmp_path / "k.json"
    path.write_text(json.dumps(values))
    return path


@pytest.mark.parametrize("content", ['{"fx": 400, "fy": 400, "cx": 12}', "not json"])
def test_pose_command_refuses_bad_intrinsics_in_one_line(tmp_path, content):
    path = tmp_path / "k.json"
    path.write_text(content)
    result = CliRunner().invoke(
        app, ["pose", "simulate3d", "-o", str(tmp_path / "out"), "--intrinsics", str(path)]
    )
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "k.json" in lines[0], result.output
    assert not (tmp_path / "out").exists()


@needs_pycolmap
@pytest.mark.parametrize(
    "overrides, cause",
    [
        (["source.frames=1500"], "at least 3 x group_size"),
        (["source.frames=3000", "source.flux=0.0002"], "too dark"),
    ],
)
def test_pose_command_refuses_short_or_dark_captures_in_one_line(tmp_path, overrides, cause):
    args = [
        "-q",
        "pose",
        "simulate3d",
        "-o",
        str(tmp_path / "out"),
        "--set",
        "source.height=64",
        "--set",
        "source.width=120",
        "--set",
        "source.focal_px=100",
    ]
    for item in overrides:
        args += ["--set", item]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and cause in lines[0], result.output


@needs_pycolmap
@pytest.mark.slow
def test_pose_command_writes_every_output_and_scores_against_ground_truth(tmp_path):
    k = _intrinsics_file(tmp_path, fx=210.0, fy=210.0, cx=123.5, cy=63.5, note="ignored")
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app,
        [
            "-q",
            "pose",
            "simulate3d",
            "-o",
            str(out),
            "--intrinsics",
            str(k),
            "--set",
            "source.frames=5000",
            "--set",
            "source.height=128",
            "--set",
            "source.width=248",
            "--set",
            "source.focal_px=210",
            "--set",
            "pose_estimator.group_size=500",
            "--set",
            "pose_estimator.levels=2",
        ],
    )
    assert result.exit_code == 0, result.output
    poses = np.load(out / "poses.npy")
    assert poses.shape == (5000, 4, 4) and np.isfinite(poses).all()
    frames, exposure_poses = np.load(out / "exposure_frames.npy"), np.load(out / "exposure_poses.npy")
    assert exposure_poses.shape == (len(frames), 4, 4)
    for name in ("points.ply", "trajectory.png", "model/cameras.bin", "intrinsics.json", "spec.yaml"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "run.json").read_text())
    assert [row["level"] for row in summary["levels"]] == [1, 2]
    assert all(row["registered"] == row["exposures"] for row in summary["levels"])
    assert summary["ground_truth"]["ate_m"] < 0.01
    # the track refinement re-located the level-2 keypoints: SIFT's alone reproject at ~1 px
    assert summary["levels"][1]["track_refinement"]["pruned"] > 0
    assert summary["levels"][1]["reprojection_error_px"] < 0.5
    assert summary["intrinsics"]["used"] == {"fx": 210.0, "fy": 210.0, "cx": 123.5, "cy": 63.5}


def test_run_with_a_pose_estimator_spec_goes_to_the_pose_command(tmp_path):
    # `photonpano run` takes a spec with a pose_estimator section through the pose run:
    # its intrinsics file (relative to the spec) is read before any frame is simulated
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: {plugin: simulate3d, frames: 3000}\n"
                    "pose_estimator: {plugin: pycolmap-sfm, intrinsics: missing.json}\n")
    result = CliRunner().invoke(app, ["-q", "run", str(spec), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and str(tmp_path / "missing.json") in lines[0] and "cannot read" in lines[0], result.output
