"""Captures that used to end ``ok`` while wrong (issue 26) now end ``degraded`` or are right."""

import numpy as np
import pytest
from capture_helpers import reconstruct_simulated as _run


@pytest.mark.slow
def test_dim_zigzag_at_m500_is_degraded_and_names_its_frames():
    """The demo's photo, dim zigzag, m = 500: several pixels off; the report says where."""
    error, report = _run({"mean_intensity": 0.016, "path": "zigzag", "speed_px_per_frame": 0.03},
                         ["group_size=500"])
    assert error.rmse_px > 1.0
    assert report["status"] == "degraded"
    unc = report["frame_uncertainty"]
    flagged = ~(unc.sigma_px <= 1.0)
    # measured: every frame is 5.8-16 px off, and every frame is flagged (the held-out
    # pairs alone flagged 37 %: they see where the error changes, not its level; the last
    # level's move after the global alignment sees the rest)
    assert flagged[error.per_frame_px > 2.0].mean() > 0.9
    if not flagged.all():
        assert error.per_frame_px[flagged].mean() > error.per_frame_px[~flagged].mean()
    assert any("frames" in line and " s)" in line for line in report["warnings"])
    assert report["uncertainty"]["above_limit"]


@pytest.mark.slow
def test_a_good_capture_is_ok_with_a_calibrated_sigma():
    error, report = _run({"frames": 12_000})
    assert error.rmse_px < 0.3 and report["status"] == "ok", report["warnings"]
    sigma = report["frame_uncertainty"].sigma_px
    assert sigma.shape == error.per_frame_px.shape and np.isfinite(sigma).all()
    assert 0.8 <= np.mean(error.per_frame_px <= 2 * sigma)
    assert 1 / 3 <= np.median(sigma) / error.rmse_px <= 3
    assert report["uncertainty"]["above_limit"] == [] and report["uncertainty"]["unverified"] == []


def _levels_and_report(source: dict, overrides: list[str]):
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.spec import apply_overrides, validate_spec

    spec = validate_spec(apply_overrides({"source": {"plugin": "simulate", **source}}, overrides), PluginHost())
    capture = spec.source.build()
    report: dict = {}
    levels: list = []
    _, stats, _, _ = reconstruct(spec, capture, report=report, on_level=levels.append)
    return capture, levels, stats, report


@pytest.mark.parametrize("overrides, since", [(["levels=2"], None), (["levels=4"], 2),
                                              (["level_schemes=[pairwise]"], 2)])
def test_the_level_change_term_is_the_move_since_the_first_level_after_level_1(overrides, since):
    """Levels 2 -> last of the last level's scheme; none with two levels (level 2 moves frames by level 1's error)."""
    from photonpano.uncertainty import frame_uncertainty

    capture, results, stats, report = _levels_and_report(
        {"frames": 3000, "height": 128, "width": 248, "vibration_px": 2.0}, overrides)
    assert len({r.scheme for r in results[1:]}) == 1
    chain = stats[0]["quality"]["pose_graph_residual_px"]
    previous = results[since - 1].homographies if since is not None else None
    span = (int(results[0].groups.reference[0]), int(results[0].groups.reference[-1]))
    expected = frame_uncertainty(results[-1], capture.width, capture.height, chain, previous=previous,
                                 level_one_span=span)
    assert np.allclose(report["frame_uncertainty"].sigma_px, expected.sigma_px)
    if len(results) > 3:  # the last step alone predicts less
        last_step = frame_uncertainty(results[-1], capture.width, capture.height, chain,
                                      previous=results[-2].homographies)
        assert np.median(expected.sigma_px) > np.median(last_step.sigma_px)


@pytest.mark.slow
def test_a_fourth_level_does_not_hide_a_dark_scene_s_error():
    """The suite's dark outdoor capture with levels=4: the levels converge slowly, so the last step is small.

    When it was 0.86 px, the last step alone predicted 0.23 px and said ok. With the mosaic
    levels corrected for the template's own error: 0.175 px (levels 1-4: 1.14, 0.34, 0.20,
    0.175), median sigma 0.24 px, ``degraded``. Measured now (the pair check's rescue takes a
    translation too, 2026-11-27): 0.137 px, median sigma 0.163 px, 99.2 % of the frames
    within 2 sigma, ``ok``.
    """
    from capture_helpers import load_suite

    suite = load_suite()
    capture = next(c for c in suite.captures() if c.name == "outdoor_camera/dark")
    row = suite.run_capture(capture, overrides=["levels=4"])
    assert row["rmse"] > 0.1, row  # still an error the fourth level's move alone understates
    assert row["within_2_sigma"] >= 0.8 and row["sigma_median"] >= row["rmse"] / 2, row


@pytest.mark.slow
def test_a_camera_that_shakes_by_turning_is_followed():
    """A 5 px, 30 Hz vibration of a turning camera (its perspective changes at 30 Hz too) on the city photo.

    Measured: 0.029 px; smoothing the shape ten times harder (``shape_smoothness: 10``) 0.065 px,
    the perspective alone ten times harder 0.084 px.
    """
    from pathlib import Path

    city = Path(__file__).resolve().parents[1] / "benchmarks" / "photos" / "city_madison.jpg"
    error, report = _run({"photo": str(city), "frames": 8000, "vibration_model": "rotation"})
    assert error.rmse_px < 0.05, error.rmse_px
    assert report["status"] == "ok", report["warnings"]


@pytest.mark.slow
def test_a_checkerboard_under_a_lamp_is_right_not_confidently_wrong(tmp_path):
    """A flat scene of hard edges: level 1's rescues scaled one axis until they were decided together.

    scikit-image's checkerboard, panned under a 100 Hz lamp (the outside check's capture):
    SIFT registers none of level 1's pairs and the binned check rescues them. Each rescue
    took the affine correction, whose vertical scale the frames' rows do not pin; the run
    ended ``ok`` at 0.605 px RMSE with a median sigma of 0.189. The level's rescues show no
    turn or zoom, so they take their translations (0.038 px measured, 2026-11-28).
    """
    import cv2
    from skimage.data import checkerboard

    photo = tmp_path / "checkerboard.png"
    cv2.imwrite(str(photo), checkerboard())
    levels: list = []
    error, report = _run({"photo": str(photo), "frames": 20_000, "flux": 0.5, "vibration_px": 5.0,
                          "vibration_hz": 30.0, "flicker_hz": 100.0, "flicker_depth": 0.6, "flicker_region": "all"},
                         levels=levels)
    check = levels[0]["registration_check"]
    assert check["rescued"] > 100 and check["rescue_motion"] == "translation", check
    assert error.rmse_px < 0.15
    assert report["status"] == "ok" and 1 / 3 <= np.median(report["frame_uncertainty"].sigma_px) / error.rmse_px <= 3
