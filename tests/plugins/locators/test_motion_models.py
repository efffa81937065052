"""Robust motion fitting with GRIC model selection (plugins/locators/matching.robust_motion)."""

from pathlib import Path

import numpy as np
import pytest
from photonpano import geometry
from photonpano.plugins.locators.matching import gric, robust_motion

W, H = 384, 384


def _corner_error(h, truth):
    c = geometry.corners(W, H)
    return float(np.abs(geometry.apply(h, c) - geometry.apply(truth, c)).max())


def test_a_thin_static_band_and_a_moving_object_give_the_static_motion():
    """The real Photron clip's configuration: a textured band at the bottom, a falling ball.

    A homography fits the band's keypoints and the ball's few keypoints at once (the band
    leaves its perspective terms free); GRIC prefers the lower-order model of the band.
    The counts are the clip's (24 band and 4 ball matches between merged frames 0 and 1):
    GRIC charges each extra degree of freedom ln(4n) ~ 4.7, an outlier at most 4, so with
    more than about 5 keypoints on the moving object the bent homography would win.
    """
    rng = np.random.default_rng(0)
    band = np.column_stack([rng.uniform(10, 374, 24), rng.uniform(335, 375, 24)])
    ball = np.column_stack([rng.uniform(150, 200, 4), rng.uniform(80, 130, 4)])
    src = np.vstack([band, ball]).astype(np.float32)
    dst = np.vstack([band, ball + [0.0, -8.0]]) + rng.normal(0, 0.1, (28, 2))
    dst = dst.astype(np.float32)
    bent = robust_motion(src, dst, motion="homography")
    auto = robust_motion(src, dst, motion="auto")
    assert _corner_error(bent.homography, np.eye(3)) > 5.0  # the degenerate fit follows the ball
    assert auto.ok and _corner_error(auto.homography, np.eye(3)) < 0.5
    assert auto.inliers == 24


def test_auto_keeps_the_homography_where_perspective_is_measurable():
    rng = np.random.default_rng(1)
    truth = np.array([[1.02, 0.01, 4.0], [-0.01, 0.99, -3.0], [4e-5, -3e-5, 1.0]])
    src = rng.uniform([0, 0], [W, H], (300, 2))
    dst = geometry.apply(truth, src) + rng.normal(0, 0.3, (300, 2))
    dst[:30] += rng.uniform(-40, 40, (30, 2))  # wrong matches
    result = robust_motion(src.astype(np.float32), dst.astype(np.float32), motion="auto")
    assert result.ok and _corner_error(result.homography, truth) < 0.5
    affine = robust_motion(src.astype(np.float32), dst.astype(np.float32), motion="affine")
    assert _corner_error(affine.homography, truth) > 2.0  # the perspective a lower model misses


def test_gric_charges_parameters_and_caps_outliers():
    src = np.random.default_rng(2).uniform(0, 100, (50, 2)).astype(np.float32)
    exact = gric(np.eye(3), src, src, 0.5, 4)
    assert gric(np.eye(3), src, src, 0.5, 8) - exact == pytest.approx(np.log(4 * 50) * 4)
    far = src + np.float32(1000)
    assert gric(np.eye(3), src, far, 0.5, 4) - exact == pytest.approx(4.0 * 50)  # each outlier costs 2 (r - d)


def test_auto_needs_inliers_for_each_extra_parameter(monkeypatch):
    """A real pair of level-1 merged frames at flux 0.05 (tests/data/SOURCES.md): 38 matches, mostly wrong.

    The camera slid (a translation), but a homography gathers 17 inliers to the
    similarity's 12 and wins GRIC by 0.9; its perspective bends the frame corners by
    almost 4 px, and a chain of pairs carries that into every later frame. With too few
    inliers per degree of freedom (``INLIERS_PER_PARAMETER``) it is no candidate.
    """
    import photonpano.plugins.locators.matching as matching

    data = np.load(Path(__file__).parents[2] / "data" / "sparse_matches_room.npz")
    src, dst = data["src"], data["dst"]
    c = geometry.corners(248, 127)

    def apart(a, b):
        return float(np.abs(geometry.apply(a.homography, c) - geometry.apply(b.homography, c)).max())

    similarity = robust_motion(src, dst, motion="similarity", threshold_px=0.75)
    bent = robust_motion(src, dst, motion="homography", threshold_px=0.75)
    assert bent.inliers > similarity.inliers and bent.inliers < 24 and apart(bent, similarity) > 3.0
    auto = robust_motion(src, dst, motion="auto", threshold_px=0.75)
    assert auto.ok and apart(auto, similarity) < 0.05
    monkeypatch.setattr(matching, "INLIERS_PER_PARAMETER", 0)  # GRIC alone: the bent homography
    assert apart(robust_motion(src, dst, motion="auto", threshold_px=0.75), bent) < 0.05
