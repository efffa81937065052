"""Flicker found in the photon counts (issue 28): frequency, per-region depth, partial or whole field.

Each capture is 8 000 binary frames of 96x192 at 100 kHz (0.08 s: 8-10 lamp periods),
panning with a 30 Hz vibration, from the bundled photo.
"""

import numpy as np
import pytest
from photonpano.flicker import MIN_DEPTH, detect_flicker
from photonpano.plugins.sources.simulate import SimulateConfig
from photonpano.quality import assess

BASE = dict(frames=8000, height=96, width=192, flux=0.5, vibration_px=5.0, vibration_hz=30.0)


def _capture(**nuisance):
    return SimulateConfig(**{**BASE, **nuisance}).build()


def test_a_lamp_over_the_right_half_is_found_with_its_frequency_and_side():
    found = detect_flicker(_capture(flicker_hz=120.0, flicker_depth=0.9, flicker_region="right"))
    assert found is not None and found.frequency_hz == pytest.approx(120.0, abs=2.0)
    depth = found.depth
    assert (depth[:, 2] > 0.6).all(), depth  # the lit side dims to ~10 % (0.8 over eighths of a period)
    assert (depth[:, 0] < MIN_DEPTH).all(), depth  # the steady side
    assert found.partial
    record = found.record()
    assert "middle-right" in record["regions"] and "middle-left" not in record["regions"]


def test_whole_field_flicker_is_found_and_not_partial():
    found = detect_flicker(_capture(flicker_hz=100.0, flicker_depth=0.6))
    assert found is not None and found.frequency_hz == pytest.approx(100.0, abs=2.0)
    assert found.flickering.all() and not found.partial
    assert np.ptp(found.depth) < 0.1 and 0.35 < found.depth.mean() < 0.6, found.depth


@pytest.mark.parametrize("settings", [{}, {"vibration_hz": 45.0, "vibration_px": 4.0}, {"flux": 0.005},
                                      {"mover_radius_px": 20.0, "mover_speed_px_per_frame": 0.08}])
def test_steady_light_is_not_flicker(settings):
    """Camera shake (30 and 45 Hz, with harmonics), photon noise and a moving object are no lamp."""
    assert detect_flicker(_capture(**settings)) is None


def test_a_short_or_slow_capture_is_not_analysed():
    assert detect_flicker(SimulateConfig(**{**BASE, "frames": 300}).build()) is None
    assert detect_flicker(SimulateConfig(**{**BASE, "frame_rate_hz": 1000.0}).build()) is None


def test_partial_flicker_makes_the_run_degraded_and_whole_field_flicker_does_not():
    from photonpano.adaptive import GroupPlan

    plan = GroupPlan(300, 1, 30.0, 0.01, 3.0, "test", True, None)
    partial = {"frequency_hz": 120.0, "depth": [[0.0, 0.4, 0.8]] * 3, "partial": True,
               "regions": ["top-right", "middle-right"]}
    status, warnings = assess(plan, [], None, None, partial)
    assert status == "degraded" and "120 Hz" in warnings[0] and "top-right" in warnings[0]
    whole = {**partial, "depth": [[0.5] * 3] * 3, "partial": False}
    assert assess(plan, [], None, None, whole) == ("ok", [])
