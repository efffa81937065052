"""The ``simulate`` source's real-scene nuisances: lamp flicker, a moving disc, hot pixels, dark counts.

Each test measures the nuisance in the photons of a small capture (2 000 frames of 64x128
from a 600-pixel-wide scene).
"""

import hashlib

import numpy as np
import pytest
from photonpano.plugins.sources.simulate import SimulateConfig
from pydantic import ValidationError

# 10 kHz: 2 000 frames are 0.2 s, 20 periods of a 100 Hz lamp
BASE = dict(frames=2000, height=64, width=128, scene_width=600, vibration_px=0.0, speed_px_per_frame=0.02,
            frame_rate_hz=10_000.0)

# sha256 of the cube of SimulateConfig(frames=300, height=32, width=64, scene_width=400, vibration_px=2.0),
# taken before the nuisances existed
DEFAULT_CUBE_SHA256 = "d05ceb1563f3d59fb9c37349bb1d785c168b9393135bcfd2a9f750793b7fd3b5"


def _bits(capture):
    return np.unpackbits(capture.cube, axis=-1)


@pytest.fixture(scope="module")
def plain():
    """The base capture without nuisances."""
    return SimulateConfig(**BASE).build()


def test_defaults_leave_the_capture_bit_identical():
    small = dict(frames=300, height=32, width=64, scene_width=400, vibration_px=2.0)
    cube = SimulateConfig(**small).build().cube
    assert hashlib.sha256(cube.tobytes()).hexdigest() == DEFAULT_CUBE_SHA256
    # the nuisances' other settings do nothing while they are switched off
    off = SimulateConfig(**small, flicker_depth=0.3, flicker_region="left", mover_speed_px_per_frame=1.0,
                         mover_intensity=0.5, mover_direction_deg=45, hot_pixel_rate=0.9).build()
    np.testing.assert_array_equal(off.cube, cube)
    assert off.mover_centres is None and off.hot_pixel_mask is None
    assert off.name == "simulate(office_equirect.jpg, pan, flux 0.5)"


def _spectrum(series, rate_hz):
    """Frequencies and power of ``series`` less a cubic trend (a pan drifts the content slowly)."""
    x = np.linspace(-1, 1, len(series))
    power = np.abs(np.fft.rfft(series - np.polyval(np.polyfit(x, series, 3), x))) ** 2
    return np.fft.rfftfreq(len(series), 1 / rate_hz), power


def test_flicker_modulates_the_lit_half_at_its_frequency_and_depth():
    # static camera, weak light (P(1) nearly linear in the intensity); the right half of the
    # scene is lit by a 100 Hz lamp: frame columns right of the centre line plus the 10 px
    # half-ramp see it, those left of it do not
    depth, hz = 0.9, 100.0
    cap = SimulateConfig(**{**BASE, "speed_px_per_frame": 0.0}, flux=0.1, flicker_hz=hz, flicker_depth=depth,
                         flicker_region="right").build()
    assert cap.name.endswith("flicker 100 Hz right)")
    bits = _bits(cap)
    lit = bits[:, :, 76:].mean(axis=(1, 2))
    unlit = bits[:, :, :52].mean(axis=(1, 2))
    freqs, lit_power = _spectrum(lit, cap.frame_rate_hz)
    _, unlit_power = _spectrum(unlit, cap.frame_rate_hz)
    peak = freqs[np.argmax(lit_power[1:]) + 1]
    assert abs(peak - hz) <= freqs[1]
    at = int(np.argmin(np.abs(freqs - hz)))
    assert lit_power[at] > 1000 * np.median(lit_power[1:])  # about 12 000x
    assert unlit_power[at] < 10 * np.median(unlit_power[1:])  # noise only

    # depth: the lit series against the lamp's waveform |sin(pi f t)| (per-frame exposure
    # mean) is y = k (1 - d + d s), so d = slope / (intercept + slope)
    s = (cap.lamp - (1 - depth)) / depth
    slope, intercept = np.polyfit(s, lit, 1)
    assert abs(slope / (intercept + slope) - depth) < 0.05
    assert np.all((cap.lamp >= 1 - depth) & (cap.lamp <= 1))
    np.testing.assert_allclose(cap.lamp.max(), 1, atol=1e-3)
    np.testing.assert_allclose(cap.lamp.min(), 1 - depth, atol=0.02)  # a frame's mean at the trough

    # scene_flux: the lit half at the lamp's mean level over the capture, 1 - d (1 - 2 / pi)
    steady = SimulateConfig(**{**BASE, "frames": 1}, flux=0.1).build().scene_flux
    ratio = cap.scene_flux / np.maximum(steady, 1e-6)
    centre = (steady.shape[1] - 1) / 2
    np.testing.assert_allclose(np.median(ratio[:, int(centre) + 11:]), 1 - depth * (1 - 2 / np.pi), atol=1e-3)
    np.testing.assert_allclose(np.median(ratio[:, :int(centre) - 10]), 1, atol=1e-6)


def test_the_lamp_region_moves_with_the_scene():
    # a pan of 0.05 px/frame moves the scene's centre line 100 px left across the frame:
    # the frame's middle columns are unlit at first and lit at the end
    cap = SimulateConfig(**{**BASE, "speed_px_per_frame": 0.05}, flicker_hz=100.0, flicker_region="right").build()
    middle = _bits(cap)[:, :, 56:72].mean(axis=(1, 2))
    freqs, first = _spectrum(middle[:600], cap.frame_rate_hz)
    _, last = _spectrum(middle[-600:], cap.frame_rate_hz)
    at = int(np.argmin(np.abs(freqs - 100.0)))
    assert last[at] > 1000 * np.median(last[1:])  # about 4 500x
    assert first[at] < 10 * np.median(first[1:])


def test_moving_disc_is_bright_inside_its_track_and_nothing_outside(plain):
    radius, flux = 8.0, 0.5
    cap = SimulateConfig(**BASE, mover_radius_px=radius, mover_speed_px_per_frame=0.1, mover_direction_deg=10).build()
    assert cap.name.endswith("mover r8)")
    centres = cap.mover_centres
    assert centres.shape == (2000, 2)
    np.testing.assert_allclose(centres[1000] + centres[999], 2 * np.array([599 / 2, (240 - 1) / 2]))
    step = 0.1 * np.array([np.cos(np.deg2rad(10)), np.sin(np.deg2rad(10))])
    np.testing.assert_allclose(np.diff(centres, axis=0), np.broadcast_to(step, (1999, 2)), atol=1e-9)
    # the disc's centre in frame pixels per frame, and every frame pixel's distance from it
    homog = np.column_stack([centres, np.ones(len(centres))])
    inside_frame = np.einsum("tij,tj->ti", np.linalg.inv(cap.ground_truth), homog)[:, :2].astype(np.float32)
    ys, xs = np.mgrid[:64, :128].astype(np.float32)
    dist = np.hypot(xs[None] - inside_frame[:, 0, None, None], ys[None] - inside_frame[:, 1, None, None])
    with_disc, without = _bits(cap), _bits(plain)
    core = dist < radius - 1
    assert core.sum() > 50_000  # the disc crosses the frame
    # inside: the disc's own rate, 1 - exp(-flux * mover_intensity), well above the scene behind it
    expected = 1 - np.exp(-flux)
    assert abs(with_disc[core].mean() - expected) < 0.01
    assert with_disc[core].mean() - without[core].mean() > 0.1
    # beyond the anti-aliased edge the photons are exactly those of the capture without the disc
    outside = dist > radius + 0.5 + 1e-3
    np.testing.assert_array_equal(with_disc[outside], without[outside])
    # scene_flux is the static scene's
    np.testing.assert_array_equal(cap.scene_flux, plain.scene_flux)


def test_hot_pixels_fire_at_their_rate_and_leave_the_others_alone(plain):
    cap = SimulateConfig(**BASE, hot_pixel_fraction=0.01, hot_pixel_rate=0.5).build()
    mask = cap.hot_pixel_mask
    assert mask.shape == (64, 128) and mask.sum() == round(0.01 * 64 * 128)
    bits = _bits(cap)
    rates = bits[:, mask].mean(axis=0)
    assert abs(rates.mean() - 0.5) < 0.01
    assert np.all(np.abs(rates - 0.5) < 0.06)  # 5 sigma of 2 000 frames
    np.testing.assert_array_equal(bits[:, ~mask], _bits(plain)[:, ~mask])
    np.testing.assert_array_equal(cap.scene_flux, plain.scene_flux)
    # fixed on the sensor and drawn from the seed
    again = SimulateConfig(**{**BASE, "frames": 1}, hot_pixel_fraction=0.01).build()
    np.testing.assert_array_equal(again.hot_pixel_mask, mask)
    always = SimulateConfig(**{**BASE, "frames": 50}, hot_pixel_fraction=0.001, hot_pixel_rate=1.0).build()
    assert _bits(always)[:, always.hot_pixel_mask].all()


def test_dark_counts_add_to_the_photon_rate():
    # a nearly black scene: every pixel fires at 1 - exp(-dark_count_rate)
    cap = SimulateConfig(**{**BASE, "frames": 500}, flux=1e-5, dark_count_rate=0.2).build()
    assert abs(_bits(cap).mean() - (1 - np.exp(-0.2))) < 0.003
    assert cap.name.endswith("dark counts 0.2)")


def test_nuisance_settings_are_validated():
    for bad in (dict(flicker_hz=-1), dict(flicker_depth=1.5), dict(flicker_region="middle"),
                dict(mover_radius_px=-1), dict(mover_speed_px_per_frame=-0.1), dict(mover_intensity=0),
                dict(mover_direction_deg=float("nan")), dict(hot_pixel_fraction=0.2), dict(hot_pixel_rate=0),
                dict(dark_count_rate=-0.1)):
        with pytest.raises(ValidationError, match=next(iter(bad))):
            SimulateConfig(**bad)
    # a disc that does not move is fine
    cap = SimulateConfig(**{**BASE, "frames": 10}, mover_radius_px=5, mover_speed_px_per_frame=0).build()
    assert np.ptp(cap.mover_centres, axis=0).max() == 0


def test_a_rotating_camera_moves_the_centre_like_the_translation_and_the_corners_by_perspective():
    """vibration_model rotation: the frame centre follows the same circle; the corners move up to ~2.2 px more."""
    from photonpano import geometry
    from photonpano.plugins.sources._simulated_scene import camera_path

    settings = dict(BASE, vibration_px=5.0, vibration_hz=300.0, width=496, height=254, scene_width=1440)
    sliding, turning = SimulateConfig(**settings), SimulateConfig(**settings, vibration_model="rotation")
    shape = (800, 1440)
    a, b = camera_path(sliding, shape), camera_path(turning, shape)
    centre = np.array([[(496 - 1) / 2, (254 - 1) / 2]])
    np.testing.assert_allclose(geometry.apply(b, centre), geometry.apply(a, centre), atol=0.05)
    frame_corners = geometry.corners(496, 254)
    corners = np.linalg.norm(geometry.apply(b, frame_corners) - geometry.apply(a, frame_corners), axis=-1)
    # a yaw of atan(5 / 420) alone moves a corner 5 x^2 / f^2 = 1.7 px further; with the pitch, up to 2.2 px
    assert 2.0 < corners.max() < 2.5
    # without vibration, the model changes nothing
    still = dict(settings, vibration_px=0.0)
    np.testing.assert_array_equal(camera_path(SimulateConfig(**still, vibration_model="rotation"), shape),
                                  camera_path(SimulateConfig(**still), shape))


def test_a_camera_panning_on_a_tripod_turns_and_sees_the_ends_of_the_scene_in_perspective():
    """pan_model rotation: the centre follows the pan's path; a 400 px pan at f = 420 px spans 660 px at its ends."""
    from photonpano import geometry
    from photonpano.plugins.sources._simulated_scene import camera_path

    settings = dict(frames=20_000, width=496, height=254, scene_width=1440, vibration_px=0.0)
    sliding, turning = SimulateConfig(**settings), SimulateConfig(**settings, pan_model="rotation")
    shape = (960, 1440)
    a, b = camera_path(sliding, shape), camera_path(turning, shape)
    centre = np.array([[(496 - 1) / 2, (254 - 1) / 2]])
    shift = geometry.apply(b, centre)[:, 0] - geometry.apply(b[10_000], centre)[0]
    slide = geometry.apply(a, centre)[:, 0] - geometry.apply(a[10_000], centre)[0]
    # the yaw is atan(x / f): the centre moves by f tan(atan(x / f)) = x, as the slide does
    np.testing.assert_allclose(shift, slide, atol=1e-6)
    width_at_end = np.ptp(geometry.apply(b[-1], geometry.corners(496, 254))[:, 0])
    assert 650 < width_at_end < 670 and np.ptp(geometry.apply(a[-1], geometry.corners(496, 254))[:, 0]) == 495
    corners = geometry.corners(496, 254)  # the middle frame, hardly turned, is where the slide puts it
    np.testing.assert_allclose(geometry.apply(b[10_000], corners), geometry.apply(a[10_000], corners), atol=0.01)
    with pytest.raises(ValidationError, match="pan_model"):
        SimulateConfig(**settings, pan_model="dolly")


def test_a_stop_and_go_pan_halts_at_the_middle_frame_and_peaks_at_twice_the_speed():
    """speed_swing 1: the frame centre's speed swings between 0 and twice speed_px_per_frame, once per period."""
    from photonpano import geometry
    from photonpano.plugins.sources._simulated_scene import camera_path

    settings = dict(frames=20_001, width=496, height=254, scene_width=1440, vibration_px=0.0)
    shape = (960, 1440)
    steady = camera_path(SimulateConfig(**settings), shape)
    swinging = camera_path(SimulateConfig(**settings, speed_swing=1.0, swing_period_frames=5000), shape)
    centre = np.array([[(496 - 1) / 2, (254 - 1) / 2]])
    speed = np.diff(geometry.apply(swinging, centre)[:, 0, 0])
    np.testing.assert_allclose([speed.min(), speed.max()], [0.0, 0.04], atol=1e-6)
    assert abs(speed[9_999]) < 1e-6 and abs(speed[4_999]) < 1e-6  # halts at the middle frame, and a period before
    assert abs(speed[7_499] - 0.04) < 1e-6  # fastest half a period from a halt
    # the swing only moves the frames along the pan: both paths meet at the middle frame
    np.testing.assert_allclose(swinging[10_000], steady[10_000], atol=1e-9)
    np.testing.assert_array_equal(camera_path(SimulateConfig(**settings, swing_period_frames=5000), shape), steady)
    with pytest.raises(ValidationError, match="speed_swing"):
        SimulateConfig(**settings, speed_swing=1.5)
