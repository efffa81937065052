"""Locators against real image pairs with known homographies."""

import cv2
import numpy as np
from locator_cases import DATA, H_TARGET_TO_SOURCE
from photonpano import geometry
from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig
from photonpano.stages import MergedFrames


def _frames(*images):
    gray = np.stack([cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in images])
    flux = gray.astype(np.float32)
    return MergedFrames(flux=flux, frames=np.ones_like(flux), images=gray, masks=np.ones(gray.shape, bool))


def _corner_error(h, truth, width, height):
    c = geometry.corners(width, height)
    return np.linalg.norm(geometry.apply(h, c) - geometry.apply(truth, c), axis=-1).mean()


def test_opencv_sift_recovers_a_real_projective_warp():
    source, target = cv2.imread(str(DATA / "source.png")), cv2.imread(str(DATA / "target.png"))
    merged = _frames(source, target)
    # pair (a=0, b=1): the homography maps target (b) pixels to source (a) pixels
    for refine in ("lm", "ecc"):
        result = OpenCVSiftConfig(refine=refine).build().register_pairs(merged, np.array([[0, 1]]), np.eye(3)[None])
        assert result.ok[0] and result.inliers[0] > 50
        h, w = target.shape[:2]
        assert _corner_error(result.homographies[0], H_TARGET_TO_SOURCE, w, h) <= 0.5


def test_opencv_sift_flags_unrelated_frames_instead_of_raising():
    rng = np.random.default_rng(0)
    noise = [(rng.random((120, 160, 3)) * 255).astype(np.uint8) for _ in range(2)]
    blank = np.zeros((120, 160, 3), np.uint8)
    merged = _frames(noise[0], noise[1], blank)
    result = OpenCVSiftConfig().build().register_pairs(merged, np.array([[0, 1], [1, 2]]), np.stack([np.eye(3)] * 2))
    assert not result.ok.any()
    assert result.homographies.shape == (2, 3, 3)
