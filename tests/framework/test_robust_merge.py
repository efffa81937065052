"""The robust merge of the compositors: a moving object left out of the panorama (issue 28)."""

import numpy as np
import pytest
from photonpano.robust_merge import exposure_bounds, exposure_index, robust_combine


def _exposures(rng, k=16, shape=(80, 120), frames=600, disc_in=(3, 4)):
    """K exposures of a textured static scene (binomial counts), a bright disc in ``disc_in``."""
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    p = 0.2 + 0.15 * np.sin(xx / 4.0) * np.cos(yy / 6.0)
    disc = (yy - 40) ** 2 + (xx - 60) ** 2 <= 12 ** 2
    sums = np.empty((k, *shape), np.float32)
    for i in range(k):
        pi = np.where(disc, 0.7, p) if i in disc_in else p
        sums[i] = rng.binomial(frames, pi)
    return sums, np.full((k, *shape), frames, np.float32), p, disc


def test_a_disc_seen_in_two_exposures_is_left_out_and_the_rest_kept():
    rng = np.random.default_rng(3)
    sums, frames, p, disc = _exposures(rng)
    kept_s, kept_n, moving = robust_combine(sums, frames)
    assert moving[disc].all()
    yy, xx = np.mgrid[:80, :120]
    far = (yy - 40) ** 2 + (xx - 60) ** 2 > (12 + 12) ** 2  # beyond the smoothing and margin
    assert moving[far].mean() < 0.005
    merged = kept_s / kept_n
    plain = sums.sum(0) / frames.sum(0)
    # inside the disc the plain merge is pulled up by 2/16 of (0.7 - p); the robust one is not
    assert np.abs(plain[disc] - p[disc]).mean() > 0.04
    assert np.abs(merged[disc] - p[disc]).mean() < 0.01
    np.testing.assert_array_equal(kept_s[far], sums.sum(0)[far])  # nothing changed away from it


def test_noise_and_a_global_gain_are_no_disagreement():
    rng = np.random.default_rng(4)
    sums, frames, _, _ = _exposures(rng, disc_in=())
    sums[5] = rng.binomial(600, np.clip(1.3 * sums[0] / 600, 0, 1))  # a brighter lamp in one exposure
    _, _, moving = robust_combine(sums, frames)
    assert moving.mean() < 0.005


def test_shapes_and_exposure_indices():
    with pytest.raises(ValueError, match="must both be"):
        robust_combine(np.zeros((4, 5, 6), np.float32), np.zeros((4, 5, 7), np.float32))
    s, n, moving = robust_combine(np.ones((2, 5, 6), np.float32), np.ones((2, 5, 6), np.float32))
    assert s.shape == (5, 6) and not moving.any() and float(n.sum()) == 60
    edges = np.array([0, 10, 990, 1000, 2500, 4000])
    np.testing.assert_array_equal(exposure_index(edges, exposure_bounds(4000, 4)), [0, 0, 0, 1, 3])
    np.testing.assert_array_equal(exposure_bounds(4000, 4), [0, 1000, 2000, 3000, 4000])
    np.testing.assert_array_equal(exposure_bounds(15, 16), np.arange(16))  # a frame each, at most
    np.testing.assert_array_equal(exposure_bounds(4000, 3, frame_step=64), [0, 1344, 2688, 4000])  # ceil to blocks


@pytest.mark.parametrize(("frames", "exposures", "period", "length", "count"), [
    (20_000, 16, 1000.0, 1000, 20),  # 100 Hz at 100 kHz: one period each (1 250 frames would be 1.25)
    (20_000, 16, 100_000 / 120, 100_000 / 120, 24),  # 120 Hz: a fractional period
    (100_000, 16, 1000.0, 6000, 16),  # six periods each, the 4 000 frames left over in the last
    (20_000, 16, 837.6, 837.6, 23),  # the 119.4 Hz lamp of the outdoor camera
    (2_000, 16, 1000.0, 1000, 2),  # shorter than three periods: too few to compare (robust_rejection)
])
def test_exposures_span_whole_flicker_periods(frames, exposures, period, length, count):
    """With a lamp's period, every exposure but the last spans the same whole number of periods, to a frame."""
    bounds = exposure_bounds(frames, exposures, period_frames=period)
    assert bounds[0] == 0 and bounds[-1] == frames and len(bounds) == count + 1
    np.testing.assert_allclose(bounds[1:-1], np.arange(1, count) * length, atol=0.5)
    assert length - 0.5 <= np.diff(bounds)[-1] < 2 * length


def test_compose_breaks_sub_batches_only_at_the_exposures():
    """A static camera makes one sub-batch of the whole capture; the robust merge needs one per exposure."""
    from photonpano.compose import BilinearCompositor, compose
    from photonpano.stages import Compositor

    class Recorder(BilinearCompositor):
        def feed_ranges(self, edges, counts, homographies):
            seen.extend(np.asarray(edges).tolist())
            super().feed_ranges(edges, counts, homographies)

        def fork(self):
            return None

    class Source:
        kind, exposure_s, frame_step, width, height, n_frames = "intensity", 1e-5, 1, 8, 6, 12

        def sum_ranges(self, edges):
            return np.ones((len(edges) - 1, 6, 8), np.float32) * np.diff(edges)[:, None, None]

    still = np.repeat(np.eye(3)[None], 12, axis=0)
    for exposures, want in ((None, {0, 12}), (4, {0, 3, 6, 9, 12})):
        seen = []
        pano = compose(Source(), still, Recorder(exposures=exposures), canvas_shape=(6, 8))
        assert set(seen) == want, (exposures, seen)
        np.testing.assert_allclose(pano.flux, 1.0)
    assert Compositor.frame_breaks(Recorder(), 12) is None  # the base: anywhere


def test_the_compositors_merge_a_mover_out_and_leave_a_static_capture_alone():
    """A small simulated pan with a bright disc crossing it, composited with the true motion."""
    import cv2
    from photonpano.compose import canvas_homographies, compose
    from photonpano.metrics import psnr, scene_on_canvas
    from photonpano.plugins.compositors.drizzle import DrizzleConfig
    from photonpano.plugins.compositors.flux_canvas import FluxCanvasConfig
    from photonpano.plugins.sources.simulate import SimulateConfig

    base = {"frames": 4000, "height": 96, "width": 160, "scene_width": 480, "flux": 0.5,
            "speed_px_per_frame": 0.02}
    static = SimulateConfig(**base).build()
    mover = SimulateConfig(**base, mover_radius_px=14.0, mover_speed_px_per_frame=0.15).build()
    to_canvas, shape = canvas_homographies(static.ground_truth, static.width, static.height, 1.0)
    scene = scene_on_canvas(static, to_canvas[0] @ np.linalg.inv(static.ground_truth[0]), shape)
    for config in (FluxCanvasConfig, DrizzleConfig):
        panos = {(name, robust): compose(src, to_canvas, config(robust=robust).build(), canvas_shape=shape)
                 for name, src in (("static", static), ("mover", mover)) for robust in (False, True)}
        assert panos["static", False].moving is None
        both = np.isfinite(scene)
        for pano in panos.values():
            both &= np.isfinite(pano.flux)
        mask = cv2.erode(both.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        db = {key: psnr(pano.flux, scene, mask) for key, pano in panos.items()}
        assert db["mover", False] < db["static", False] - 0.4, (config, db)  # the streak
        # merged out (drizzle: 0.11 dB below, at 33.9 dB; with the restoration's former stride of
        # 2, 0.09 dB below at 33.6 dB)
        assert db["mover", True] > db["static", False] - 0.15, (config, db)
        # no cost when static (drizzle's Wiener restoration, whose deblurring lifts the few
        # canvas pixels where a run of frames was left out by chance: 0.042 dB below, at 33.9 dB)
        assert abs(db["static", True] - db["static", False]) < 0.05, (config, db)
        assert panos["mover", True].moving.mean() > 5 * max(panos["static", True].moving.mean(), 1e-4)


def test_exposures_of_whole_flicker_periods_see_no_mover_in_a_half_lit_static_scene():
    """A 100 Hz lamp over the right half: runs of 0.8 periods read its beat as movers; whole periods do not."""
    import cv2
    from photonpano.compose import canvas_homographies, compose
    from photonpano.metrics import psnr, scene_on_canvas
    from photonpano.plugins.compositors.drizzle import DrizzleConfig
    from photonpano.plugins.sources.simulate import SimulateConfig

    capture = SimulateConfig(frames=8000, height=96, width=160, scene_width=480, flux=0.5, speed_px_per_frame=0.02,
                             flicker_hz=100.0, flicker_depth=0.9, flicker_region="right").build()
    to_canvas, shape = canvas_homographies(capture.ground_truth, capture.width, capture.height, 1.0)
    scene = scene_on_canvas(capture, to_canvas[0] @ np.linalg.inv(capture.ground_truth[0]), shape)
    panos = {}
    for name in ("plain", "robust", "whole periods"):
        compositor = DrizzleConfig(robust=name != "plain", robust_exposures=10).build()  # 800 frames each
        if name == "whole periods":
            compositor.expect_flicker(capture.frame_rate_hz / 100.0)  # 8 exposures of 1 000 frames
        panos[name] = compose(capture, to_canvas, compositor, canvas_shape=shape)
    mask = cv2.erode(np.isfinite(scene + panos["plain"].flux).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    db = {name: psnr(pano.flux, scene, mask) for name, pano in panos.items()}
    moving = {name: float(pano.moving.mean()) for name, pano in panos.items() if pano.moving is not None}
    assert moving["robust"] > 0.05, moving  # the lamp's beat between runs left out as movers (0.16)
    assert moving["whole periods"] < 0.002 and db["whole periods"] > db["plain"] - 0.02, (moving, db)  # 0, 0.00


def test_the_compiled_weighted_median_is_the_sorted_cumulative_weight_one():
    """Against the numpy form (argsort, cumulative weight, first value reaching half): NaNs, ties, zero weights."""
    from photonpano.robust_merge import _weighted_median

    rng = np.random.default_rng(5)
    values = rng.integers(0, 6, (16, 40, 50)).astype(np.float32)  # ties
    weights = (rng.random((16, 40, 50)) * 50).astype(np.float32)
    values[rng.random(values.shape) < 0.1] = np.nan
    weights[rng.random(weights.shape) < 0.1] = 0
    values[:, 0, 0] = np.nan  # nothing with weight: NaN
    weights[:, 0, 1] = 0

    w = np.where(np.isfinite(values), weights, 0).astype(np.float32)
    order = np.argsort(np.where(w > 0, values, np.inf), axis=0, kind="stable")
    cumulative = np.cumsum(np.take_along_axis(w, order, axis=0), axis=0)
    half = 0.5 * cumulative[-1]
    pick = np.minimum(np.sum(cumulative < half[None], axis=0), len(values) - 1)
    expected = np.where(half > 0, np.take_along_axis(np.take_along_axis(values, order, axis=0), pick[None], 0)[0],
                        np.nan)
    np.testing.assert_array_equal(_weighted_median(values, weights), expected.astype(np.float32))
