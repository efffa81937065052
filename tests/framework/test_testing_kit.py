"""The contract kit (photonpano.testing) on built-in and deliberately broken plugins.

The built-in plugins of every other stage kind must pass; broken ones must be caught:
a swapped direction and a half-pixel centre convention (locators), frames painted
0.5 px off and mean counts returned as flux (compositors).
"""

from typing import Literal

import numpy as np
import pytest
from photonpano.compose import BilinearCompositor
from photonpano.plugins.interpolators.cubic_lk import CubicLKConfig
from photonpano.plugins.mergers.flux_mle import FluxMLEConfig
from photonpano.plugins.resamplers.midpoint import MidpointConfig
from photonpano.plugins.sources.npy_cube import NpyCubeConfig
from photonpano.plugins.sources.simulate import SimulateConfig
from photonpano.records import Panorama
from photonpano.stages import CompositorConfig, Locator, LocatorConfig, LocatorContext, PairRegistrations
from photonpano.testing import (
    CompositorContract,
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
    def _register_pairs(self, merged, pairs, initial, context):
        from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig

        good = OpenCVSiftConfig().build().register_pairs(merged, pairs, initial)
        return PairRegistrations(np.linalg.inv(good.homographies), good.matches, good.inliers, good.ok)


class _SwappedContract(LocatorContract):
    config_class = _SwappedConfig


def test_the_kit_catches_a_swapped_direction():
    check = _SwappedContract()
    with pytest.raises(AssertionError, match="direction swapped"):
        check.test_recovers_a_known_warp_in_the_right_direction(_SwappedConfig().build())


class _PositionsLocator(Locator):
    """A locator of the old contract: it reads pairs as positions in ``merged`` (ring slots), bypassing the ids."""

    def register_pairs(self, merged, pairs, initial, context=None):
        from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig

        return OpenCVSiftConfig().build()._register_pairs(merged, np.asarray(pairs, np.int64), initial,
                                                          LocatorContext())

    def _register_pairs(self, merged, pairs, initial, context):
        raise AssertionError("not reached: register_pairs is overridden")


def test_the_kit_catches_pairs_read_as_positions():
    """A locator that indexes ``merged`` by the pairs' values (not their frame ids) fails the kit's id check."""
    check = _SwappedContract()
    with pytest.raises(IndexError):  # ids 1000 and 42 read as positions among 3 frames
        check.test_pairs_name_frames_by_id(_PositionsLocator())


def test_the_kit_catches_a_half_pixel_centre_convention():
    """Coordinates off by (0.5, 0.5) px: 0.41 px on the perspective pair (passes 0.5 px), > 1 px on a half turn."""
    check = _HalfPixelContract()
    locator = _HalfPixelConfig().build()
    truth = check.truth()
    result = locator.register_pairs(synthetic_pair(truth), np.array([[0, 1]]), np.eye(3)[None])
    # what the kit's first pair sees of it: about the locator's own error (measured 0.41 vs 0.40 px)
    assert corner_error_px(result.homographies[0], truth, 240, 160) < check.tolerance_px
    with pytest.raises(AssertionError, match="half turn about the frame centre"):
        check.test_pixel_centres_at_integers(locator)


@pytest.mark.parametrize("compositor", ["half-pixel", "mean-counts", "detection-rate"])
def test_the_kit_catches_broken_compositors(compositor):
    """Frames painted 0.5 px off their homographies, or mean counts or detection rates as flux, fail the kit."""
    check = _BrokenCompositorContract()
    capture = tiny_capture()
    panorama = check._compose(_BrokenCompositorConfig(bug=compositor).build(), capture)
    with pytest.raises(AssertionError, match=r"PSNR 3[23]\.\d+ dB"):  # measured: 32.2, 32.8 and 32.8 dB
        check.test_panorama_has_documented_types_and_matches_the_scene(panorama, capture)
    if compositor == "half-pixel":
        with pytest.raises(AssertionError, match=r"offset by \(\+0\.[45]"):  # measured: (+0.505, -0.038) px
            check.test_frames_land_where_their_homographies_say(panorama, capture)
    else:
        with pytest.raises(AssertionError, match="not counts"):  # measured: 1e-5 x and 0.946 x the scene's flux
            check.test_flux_is_calibrated_in_photons_per_second(panorama, capture)


def test_selectable_in_a_spec_skips_naming_a_missing_extra(monkeypatch):
    """Without the plugin's optional extra the check skips with the module and install hint, not fails."""
    from photonpano.plugins.locators.kornia_sift import KorniaSiftConfig

    class _Check(LocatorContract):
        config_class = KorniaSiftConfig
        entry_point = "kornia-sift"

    config = KorniaSiftConfig()
    monkeypatch.setattr(KorniaSiftConfig, "requires", ("photonpano_no_such_module",))
    with pytest.raises(pytest.skip.Exception, match=r"needs photonpano_no_such_module: pip install"):
        _Check().test_selectable_in_a_spec(config)


class _HalfPixelConfig(LocatorConfig):
    """A locator whose coordinates put pixel centres at half-integers (x + 0.5 for x)."""

    plugin: Literal["half-pixel-test"] = "half-pixel-test"

    def build(self):
        """Return the buggy locator."""
        return _HalfPixelLocator()


class _HalfPixelLocator(Locator):
    def _register_pairs(self, merged, pairs, initial, context):
        from photonpano import geometry
        from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig

        good = OpenCVSiftConfig().build().register_pairs(merged, pairs, initial)
        half = geometry.translation(0.5, 0.5)
        return PairRegistrations(geometry.normalize(half @ good.homographies @ np.linalg.inv(half)), good.matches,
                                 good.inliers, good.ok)


class _HalfPixelContract(LocatorContract):
    config_class = _HalfPixelConfig


class _BrokenCompositorConfig(CompositorConfig):
    """A compositor with a deliberate bug: frames 0.5 px off, mean counts per frame or detections per second as flux."""

    plugin: Literal["broken-compositor-test"] = "broken-compositor-test"
    bug: Literal["half-pixel", "mean-counts", "detection-rate"] = "half-pixel"
    """Which bug."""

    def build(self):
        """Return the buggy compositor."""
        if self.bug == "half-pixel":
            return _HalfPixelCompositor()
        return _MeanCountsCompositor(per_second=self.bug == "detection-rate")


class _HalfPixelCompositor(BilinearCompositor):
    def feed(self, counts, n_frames, homographies, weights=None):
        from photonpano import geometry

        super().feed(counts, n_frames, geometry.translation(0.5, 0.0) @ homographies, weights)


class _MeanCountsCompositor(BilinearCompositor):
    def __init__(self, per_second):
        super().__init__()
        self.per_second = per_second

    def prepare(self, canvas, source):
        super().prepare(canvas, source)
        self._exposure_s = source.exposure_s

    def finish(self):
        panorama = super().finish()
        # the detection probability per binary frame, 1 - exp(-flux t): what dividing counts by frames gives;
        # divided by t, the detection rate (no Poisson inversion: low where bright)
        t = np.float32(self._exposure_s)
        mean_counts = -np.expm1(-panorama.flux * t) / (t if self.per_second else np.float32(1))
        return Panorama(flux=mean_counts.astype(np.float32), frames=panorama.frames,
                        homographies=panorama.homographies)


class _BrokenCompositorContract(CompositorContract):
    config_class = _BrokenCompositorConfig

