"""The pose estimator contract (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from ._captures import builtin_source
from ._plugin import PluginContract


class PoseEstimatorContract(PluginContract):
    """The pose estimator contract (see :meth:`photonpano.stages.PoseEstimator.estimate`).

    Runs the estimator on :meth:`make_capture` (default: a small ``simulate3d`` room of
    ``capture_frames`` frames with ground-truth poses and intrinsics) and checks the
    documented shapes, that registered poses are rigid and near the truth, and that a
    capture too short to register is a :class:`~photonpano.errors.StageError`. Set
    ``config_kwargs`` so that ``capture_frames`` frames are enough for the plugin.
    """

    capture_frames: ClassVar[int] = 4000
    max_ate_m: ClassVar[float] = 0.02
    """Largest acceptable camera-centre RMS error after similarity alignment, metres."""

    @classmethod
    def make_capture(cls, frames: int) -> Any:
        """Return a capture with ``ground_truth_poses`` and ``intrinsics`` (default: ``simulate3d``)."""
        return builtin_source("simulate3d")(frames=frames, height=128, width=248, focal_px=210.0).build()

    @pytest.fixture(scope="class")
    @classmethod
    def estimated(cls, built: Any, tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any]:
        """``(capture, PoseResult)`` of one run with the true intrinsics."""
        capture = cls.make_capture(cls.capture_frames)
        return capture, built.estimate(capture, capture.intrinsics, tmp_path_factory.mktemp("pose"))

    def test_result_shapes_and_rigid_poses(self, estimated: tuple[Any, Any]) -> None:
        """(T, 4, 4) float64 poses with rotation blocks orthonormal, last rows (0, 0, 0, 1)."""
        capture, result = estimated
        poses = result.poses
        assert poses.shape == (capture.n_frames, 4, 4) and poses.dtype == np.float64
        ok = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
        assert ok.mean() > 0.9, "most binary frames should get a pose"
        rot = poses[ok, :3, :3]
        eye = np.broadcast_to(np.eye(3), rot.shape)
        np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), eye, atol=1e-6)
        np.testing.assert_array_equal(poses[ok, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (int(ok.sum()), 4)))
        assert result.exposure_poses.shape == (len(result.exposure_frames), 4, 4)
        assert result.exposure_frames.dtype == np.int64
        assert result.points.ndim == 2 and result.points.shape[1] == 3
        assert len(result.points) == len(result.colors)

    def test_poses_match_ground_truth(self, estimated: tuple[Any, Any]) -> None:
        """Camera centres within ``max_ate_m`` of the truth after a similarity alignment."""
        from photonpano.pose import absolute_trajectory_error

        capture, result = estimated
        assert absolute_trajectory_error(result.poses, capture.ground_truth_poses) < self.max_ate_m

    def test_too_short_capture_is_a_stage_error(self, built: Any, tmp_path: Any) -> None:
        """A capture of a few frames fails with a one-line StageError."""
        from photonpano.errors import StageError

        capture = self.make_capture(64)
        with pytest.raises(StageError):
            built.estimate(capture, capture.intrinsics, tmp_path)
