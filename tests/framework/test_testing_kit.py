"""The contract kit (photonpano.testing) on built-in and deliberately broken plugins.

The built-in plugins of every other stage kind must pass; broken ones must be caught.
"""

from typing import Literal

import numpy as np
import pytest
from photonpano.plugins.interpolators.cubic_lk import CubicLKConfig
from photonpano.plugins.mergers.flux_mle import FluxMLEConfig
from photonpano.plugins.resamplers.midpoint import MidpointConfig
from photonpano.plugins.sources.npy_cube import NpyCubeConfig
from photonpano.plugins.sources.simulate import SimulateConfig
from photonpano.stages import Locator, LocatorConfig, PairRegistrations
from photonpano.testing import (
    InterpolatorContract,
    LocatorContract,
    MergerContract,
    ResamplerContract,
    SourceContract,
    corner_error_px,
    synthetic_pair,
    tiny_capture,
)


class TestSimulate(SourceContract):
    config_class = SimulateConfig
    config_kwargs = {"frames": 200, "height": 32, "width": 64}
    entry_point = "simulate"


class TestNpyCube(SourceContract):
    config_class = NpyCubeConfig
    entry_point = "npy-cube"

    def make_config(self, tmp_path_factory):
        path = tmp_path_factory.mktemp("cube") / "cube.npy"
        np.save(path, np.asarray(tiny_capture(frames=200).cube))
        return NpyCubeConfig(path=path)


class TestMidpoint(ResamplerContract):
    config_class = MidpointConfig
    entry_point = "midpoint"


class TestFluxMLE(MergerContract):
    config_class = FluxMLEConfig
    entry_point = "flux-mle"


class TestCubicLK(InterpolatorContract):
    config_class = CubicLKConfig
    entry_point = "cubic-lk"


def test_synthetic_pair_follows_the_pair_convention():
    """b(x) = a(H x): sampling frame a at H x reproduces frame b (what the kit asserts against)."""
    import cv2

    truth = np.array([[1, 0, 3.0], [0, 1, -2.0], [0, 0, 1.0]])
    merged = synthetic_pair(truth, noise=0.0, border_px=0)
    a, b = merged.flux
    pulled = cv2.warpPerspective(a, truth, a.shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    inner = (slice(10, -10), slice(10, -10))
    np.testing.assert_allclose(pulled[inner], b[inner], rtol=0.05, atol=0.02 * float(a.max()))
    assert corner_error_px(truth, np.eye(3), 240, 160) == pytest.approx(np.hypot(3, 2))


class _SwappedConfig(LocatorConfig):
    """A locator that returns the inverse homography (a classic direction bug)."""

    plugin: Literal["swapped-test"] = "swapped-test"

    def build(self):
        """Return the buggy locator."""
        return _SwappedLocator()


class _SwappedLocator(Locator):
    def register_pairs(self, merged, pairs, initial):
        from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig

        good = OpenCVSiftConfig().build().register_pairs(merged, pairs, initial)
        return PairRegistrations(np.linalg.inv(good.homographies), good.matches, good.inliers, good.ok)


class _SwappedContract(LocatorContract):
    config_class = _SwappedConfig


def test_the_kit_catches_a_swapped_direction():
    check = _SwappedContract()
    with pytest.raises(AssertionError, match="direction swapped"):
        check.test_recovers_a_known_warp_in_the_right_direction(_SwappedConfig().build())
