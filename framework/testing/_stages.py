"""The source, resampler, merger and interpolator contracts (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from ._captures import tiny_capture
from ._plugin import PluginContract


class SourceContract(PluginContract):
    """The source contract (see :class:`photonpano.stages.PhotonSource`).

    Override :meth:`make_config` to create the capture the config points at (use
    ``tmp_path_factory``); the capture should hold at least 64 frames.
    """

    def test_describes_itself(self, built: Any) -> None:
        """Positive sizes, exposure and rate; ``describe()`` is JSON-ready."""
        from photonpano.stages import PhotonSource

        assert isinstance(built, PhotonSource)
        assert built.n_frames > 0 and built.height > 0 and built.width > 0
        assert built.exposure_s > 0 and built.frame_rate_hz > 0
        json.dumps(built.describe())
        if built.ground_truth is not None:
            assert built.ground_truth.shape == (built.n_frames, 3, 3)
            assert built.ground_truth.dtype == np.float64

    def test_sum_ranges_shapes_and_additivity(self, built: Any) -> None:
        """(B, H, W) sums; the sum over a range equals the sums over its halves."""
        t = min(built.n_frames, 64) // 2 * 2
        edges = np.array([0, t // 2, t], np.int64)
        counts = built.sum_ranges(edges)
        kind = getattr(built, "kind", "binary")
        assert counts.shape == (2, built.height, built.width)
        if kind == "binary":
            assert counts.dtype == np.uint16
            assert counts.max() <= t // 2 and counts.min() >= 0
        whole = built.sum_ranges(np.array([0, t], np.int64))
        np.testing.assert_allclose(whole[0].astype(np.float64), counts.sum(0, dtype=np.float64), rtol=1e-5)


class ResamplerContract(PluginContract):
    """The resampler contract (see :meth:`photonpano.stages.Resampler.groups`)."""

    def test_groups_are_valid_on_every_level(self, built: Any) -> None:
        """References strictly increase and lie inside their groups, within the capture."""
        n, m = 5000, 250
        for level in (1, 2, 3):
            groups = built.groups(n, m, level)
            assert len(groups) >= 2
            assert groups.start.min() >= 0 and groups.stop.max() <= n
            assert np.all(np.diff(groups.reference) > 0)
            for name in ("start", "stop", "reference"):
                assert getattr(groups, name).dtype == np.int64

    def test_too_short_capture_is_a_value_error(self, built: Any) -> None:
        """Fewer than 2 * group_size frames raise ValueError (the documented error)."""
        with pytest.raises(ValueError):
            built.groups(10, 500, 1)


class MergerContract(PluginContract):
    """The merger contract (see :meth:`photonpano.stages.Merger.merge`), on :func:`tiny_capture`."""

    def test_merges_groups_with_documented_types(self, built: Any) -> None:
        """(G, H, W) float32 flux/frames, uint8 images, bool masks; trusted flux is finite."""
        from photonpano.stages import Groups

        source = tiny_capture()
        n = source.n_frames
        starts = np.arange(0, n, 300, dtype=np.int64)
        groups = Groups(start=starts, stop=np.minimum(starts + 300, n), reference=starts + 150)
        merged = built.merge(source, np.repeat(np.eye(3)[None], n, axis=0), groups)
        g, h, w = len(groups), source.height, source.width
        kinds = (("flux", np.float32), ("frames", np.float32), ("images", np.uint8), ("masks", np.bool_))
        for name, dtype in kinds:
            arr = getattr(merged, name)
            assert arr.shape == (g, h, w) and arr.dtype == dtype, f"{name}: {arr.shape} {arr.dtype}"
        assert merged.masks.mean() > 0.5
        assert np.all(np.isfinite(merged.flux[merged.masks]))
        assert np.all(merged.flux[merged.masks] >= 0)


class InterpolatorContract(PluginContract):
    """The interpolator contract (see :meth:`photonpano.stages.Interpolator.interpolate`)."""

    def test_shapes_and_normalisation(self, built: Any) -> None:
        """(T, 3, 3) float64 with ``H[2, 2] == 1`` from a few keyframes."""
        from photonpano import geometry

        keyframes = np.array([100, 300, 500, 700], np.int64)
        h = geometry.translation(0.0, 0.0)[None].repeat(4, 0)
        h[:, 0, 2] = [0.0, 2.0, 4.0, 6.0]
        out = built.interpolate(keyframes, h, 800)
        assert out.shape == (800, 3, 3) and out.dtype == np.float64
        np.testing.assert_allclose(out[:, 2, 2], 1.0)

    def test_constant_motion_stays_constant(self, built: Any) -> None:
        """Identical keyframe homographies interpolate to that homography everywhere."""
        from photonpano import geometry

        keyframes = np.array([100, 300, 500, 700], np.int64)
        h = np.repeat(geometry.translation(1.5, -0.5)[None], 4, axis=0)
        out = built.interpolate(keyframes, h, 800)
        np.testing.assert_allclose(out, np.repeat(h[:1], 800, axis=0), atol=1e-6)
