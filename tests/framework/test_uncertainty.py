"""Per-frame uncertainty from held-out registrations (issue 26): residuals, ranges, status."""

import numpy as np
import pytest
from photonpano import geometry
from photonpano.quality import _uncertainty_warnings
from photonpano.records import Groups, LevelResult, LocateResult, PairRegistrations
from photonpano.uncertainty import (
    CHAIN_DRIFT_PER_FRAME_EXTENT,
    LEVEL_CHANGE_TO_SIGMA,
    LIMIT_PX,
    NEIGHBOURS,
    RESIDUAL_TO_SIGMA,
    _local_rms,
    frame_extents_travelled,
    frame_uncertainty,
    level_change,
)

W, H = 64, 32


def _level(n_frames=1000, m=100, shift=None, failed=(), speed=0.01):
    """A mosaic-like last level (a pan at ``speed`` px/frame); its held-out pairs are off by ``shift[g]`` px."""
    ref = np.arange(m // 2, n_frames - m // 2 + 1, m // 2)
    groups = Groups(start=ref - m // 2, stop=ref + m // 2, reference=ref)
    homographies = np.stack([geometry.translation(speed * t, 0.0) for t in range(n_frames)])
    g = len(ref)
    index = np.stack([np.arange(g - 1), np.arange(1, g)], axis=1)
    truth = np.linalg.inv(homographies[ref[:-1]]) @ homographies[ref[1:]]
    shift = np.zeros(g - 1) if shift is None else np.asarray(shift, float)
    measured = np.stack([geometry.translation(s, 0.0) for s in shift]) @ truth
    ok = np.ones(g - 1, bool)
    ok[list(failed)] = False
    cross = PairRegistrations(measured, np.zeros(g - 1, np.int64), np.zeros(g - 1, np.int64), ok)
    regs = PairRegistrations(np.repeat(np.eye(3)[None], g, 0), np.zeros(g, np.int64), np.zeros(g, np.int64),
                             np.ones(g, bool))
    located = LocateResult(homographies[ref], regs, None, crosscheck=cross, crosscheck_index=index)
    return LevelResult(3, "mosaic", groups, located, homographies)


def test_local_rms_ignores_missing_values():
    values = np.array([3.0, np.nan, 4.0, np.nan, np.nan, np.nan])
    rms = _local_rms(values, 1)
    assert rms[0] == pytest.approx(3.0) and rms[1] == pytest.approx(5 / np.sqrt(2))
    assert rms[3] == pytest.approx(4.0) and np.isnan(rms[5])


def test_residuals_scale_into_sigma_for_every_frame():
    """Held-out pairs off by 0.1 px predict RESIDUAL_TO_SIGMA x 0.1 px everywhere; none is unverified."""
    result = _level(shift=np.full(18, 0.1))
    unc = frame_uncertainty(result, W, H)
    assert unc.sigma_px.shape == (1000,) and unc.sigma_px.dtype == np.float64
    assert np.allclose(unc.sigma_px, RESIDUAL_TO_SIGMA * 0.1)
    assert not unc.unverified.any() and unc.evidence == "held-out pairs" and unc.failed == 0


def test_level_one_chain_residual_adds_drift_away_from_the_middle_only():
    """A pan across three frame widths: level 1's pose-graph residual per frame extent travelled, in quadrature."""
    n = 1000
    level = _level(n_frames=n, shift=np.full(18, 0.02), speed=3 * W / n)
    plain, chained = frame_uncertainty(level, W, H), frame_uncertainty(level, W, H, chain_residual_px=0.4)
    local = RESIDUAL_TO_SIGMA * 0.02
    travelled = frame_extents_travelled(level.homographies, W, H)
    assert travelled[n // 2] == 0 and travelled[0] == pytest.approx(1.5)
    assert chained.sigma_px[n // 2] == pytest.approx(plain.sigma_px[n // 2]) == pytest.approx(local)
    assert chained.sigma_px[0] == pytest.approx(np.hypot(local, CHAIN_DRIFT_PER_FRAME_EXTENT * 0.4 * 1.5))
    assert np.all(np.diff(chained.sigma_px[n // 2:]) >= 0)
    assert chained.sigma_px[0] > 3 * plain.sigma_px[0]  # precise local residuals no longer hide the chain


def test_the_last_level_moving_frames_adds_its_move_to_their_sigma():
    """Frames moved 0.8 px from the previous trajectory get LEVEL_CHANGE_TO_SIGMA x 0.8 px more, in quadrature."""
    level = _level(shift=np.full(18, 0.05))
    previous = level.homographies.copy()
    previous[200:400] = geometry.translation(0.0, 0.8) @ previous[200:400]
    unc = frame_uncertainty(level, W, H, previous=previous)
    local = RESIDUAL_TO_SIGMA * 0.05
    change = level_change(level.homographies, previous, W, H)
    assert change[300] == pytest.approx(0.8)
    assert np.allclose(unc.sigma_px, np.hypot(local, LEVEL_CHANGE_TO_SIGMA * change))
    # the global alignment spreads the move a little over the frames that did not move
    assert change[100] < 0.4 and change[500] < 0.4
    with pytest.raises(ValueError, match="previous level"):
        frame_uncertainty(level, W, H, previous=previous[:10])


def test_the_move_beyond_level_one_s_span_is_taken_at_its_ends():
    """Level 1 extrapolates beyond its first and last reference frame; the later levels' move there is its error."""
    level = _level(shift=np.full(18, 0.05))
    previous = level.homographies.copy()
    previous[:100] = geometry.translation(0.0, 1.5) @ previous[:100]  # the first mosaic level's end group, off
    local = RESIDUAL_TO_SIGMA * 0.05
    plain = frame_uncertainty(level, W, H, previous=previous)
    held = frame_uncertainty(level, W, H, previous=previous, level_one_span=(150, 900))
    change = level_change(level.homographies, previous, W, H)
    assert plain.sigma_px[0] == pytest.approx(np.hypot(local, LEVEL_CHANGE_TO_SIGMA * 1.5), rel=0.05)
    assert np.allclose(held.sigma_px[:150], np.hypot(local, LEVEL_CHANGE_TO_SIGMA * change[150]))
    assert np.allclose(held.sigma_px[901:], np.hypot(local, LEVEL_CHANGE_TO_SIGMA * change[900]))
    assert np.allclose(held.sigma_px[150:901], plain.sigma_px[150:901])
    assert held.sigma_px[0] < 0.3 < plain.sigma_px[0]


def test_a_move_shared_by_every_frame_but_the_middle_one_is_seen_at_the_middle_too():
    """The middle frame defines the panorama, so a move of all others relative to it leaves it in place."""
    level = _level(shift=np.full(18, 0.05))
    middle = len(level.homographies) // 2
    previous = geometry.translation(0.5, 0.0) @ level.homographies
    previous[middle] = level.homographies[middle]
    in_panorama = geometry.mean_corner_distance(level.homographies, previous, W, H)
    assert in_panorama[middle] == 0 and in_panorama[0] == pytest.approx(0.5)
    change = level_change(level.homographies, previous, W, H)
    assert change[middle] == pytest.approx(0.5, abs=0.01) and change.min() == pytest.approx(0.5, abs=0.01)


def test_a_jump_is_located_and_named_by_frames_and_seconds():
    """One held-out pair 6 px off: the frames between its groups exceed the limit, the warning names them.

    Its local RMS over 17 pairs is 6 / sqrt(17) = 1.46 px, times ``RESIDUAL_TO_SIGMA`` (0.3)
    0.44 px, under the limit; but one of the pair's groups is off by at least 3 px (the jump
    floor), so the frames between the two are flagged.
    """
    shift = np.full(58, 0.05)
    shift[10] = 6.0
    unc = frame_uncertainty(_level(n_frames=3000, shift=shift), W, H)
    summary = unc.summary(frame_rate_hz=1000.0)
    (above,) = summary["above_limit"]
    first, last = above["frames"]
    jump = 550 + 25  # the pair's middle frame (references 550 and 600)
    assert first < jump < last and above["seconds"] == [first / 1000, last / 1000]
    assert last - first < 2 * (NEIGHBOURS + 1) * 50 + 100  # local, not the whole capture
    assert summary["median_px"] < LIMIT_PX
    (line,) = _uncertainty_warnings(summary)
    assert f"frames {first}-{last}" in line and "px" in line


def test_failed_held_out_pairs_and_ends_are_unverified():
    unc = frame_uncertainty(_level(shift=np.full(18, 0.05), failed=[4]), W, H)
    refs = np.arange(50, 951, 50)
    assert unc.unverified[refs[4]:refs[5] + 1].all()
    assert (unc.sigma_px[unc.unverified] >= 2 * LIMIT_PX).all()
    assert not unc.unverified[refs[0]:refs[4]].any()
    assert unc.failed == 1
    lines = _uncertainty_warnings(unc.summary(1000.0))
    assert any("bridged" in line and f"frames {refs[4]}-{refs[5]}" in line for line in lines)
