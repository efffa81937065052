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


def test_blas_matcher_keeps_exactly_the_matches_of_opencvs_brute_force_matcher():
    from photonpano.plugins.locators.matching import IntegralL2Matcher, ratio_matches

    source, target = cv2.imread(str(DATA / "source.png")), cv2.imread(str(DATA / "target.png"))
    locator = OpenCVSiftConfig().build()
    gray = [cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (source, target)]
    rng = np.random.default_rng(1)
    noisy = [np.clip(g + rng.normal(0, 12, g.shape), 0, 255).astype(np.uint8) for g in gray]  # merged-frame noise
    descriptors = [locator.features(image, np.ones(image.shape, bool))[1] for image in gray + noisy]
    brute, blas = cv2.BFMatcher(cv2.NORM_L2), IntegralL2Matcher()
    kept = 0
    for i, train in enumerate(descriptors):
        assert IntegralL2Matcher.exact(train) and len(train) > 100
        for j, query in enumerate(descriptors):
            if i != j:
                for ratio in (0.6, 0.75, 0.9):
                    expected = ratio_matches(brute, query, train, ratio)
                    found = ratio_matches(blas, query, train, ratio)
                    assert np.array_equal(expected[0], found[0]) and np.array_equal(expected[1], found[1])
                    kept += len(found[0])
    assert kept > 1000
    # descriptors that are not small integers would lose the exactness: they are refused
    assert not IntegralL2Matcher.exact(descriptors[0] + np.float32(0.5))
    assert not IntegralL2Matcher.exact(descriptors[0] * np.float32(16))
    assert not IntegralL2Matcher.exact(descriptors[0].astype(np.float64))


def test_threaded_runs_keep_the_blas_to_one_thread_and_restore_it():
    from photonpano.executor import ThreadExecutor
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]

    before = blas_threads()
    assert before  # numpy's OpenBLAS is loaded
    with ThreadExecutor(2) as executor:
        inside = executor.map(lambda _: blas_threads(), range(2))
    assert all(threads == 1 for pools in inside for threads in pools)
    assert blas_threads() == before


def test_auto_feature_budget_follows_the_frame_size_not_its_texture():
    from photonpano.plugins.locators.opencv_sift import MIN_FEATURES, PIXELS_PER_FEATURE, feature_budget

    assert feature_budget("auto", (127, 248)) == 493 == -(-127 * 248 // PIXELS_PER_FEATURE)
    assert feature_budget("auto", (40, 60)) == MIN_FEATURES and feature_budget(0, (127, 248)) == 0
    # a texture-rich image: the automatic budget binds, the former default (2000) did not
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur((rng.random((127, 248)) * 255).astype(np.uint8), (3, 3), 0)
    mask = np.ones(texture.shape, bool)
    points, _ = OpenCVSiftConfig().build().features(texture, mask)
    unlimited, _ = OpenCVSiftConfig(max_features=0).build().features(texture, mask)
    assert len(unlimited) > 600 and len(points) == 493
    # and the warp is still recovered on the real pair with the budget of its size
    source, target = cv2.imread(str(DATA / "source.png")), cv2.imread(str(DATA / "target.png"))
    result = OpenCVSiftConfig().build().register_pairs(_frames(source, target), np.array([[0, 1]]), np.eye(3)[None])
    h, w = target.shape[:2]
    assert result.ok[0] and _corner_error(result.homographies[0], H_TARGET_TO_SOURCE, w, h) <= 0.5
