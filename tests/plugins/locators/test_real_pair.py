"""Every locator on a real image pair with a known strong projective warp (scale ~1.9).

Feature locators start from the identity (they ignore ``initial``); direct locators start
from the true warp with the corners moved 1.6-2.6 px, their use in the pipeline.
"""

import numpy as np
import pytest
from locator_cases import ALL_LOCATORS, DIRECT_LOCATORS, H_TARGET_TO_SOURCE, need_backend, perturbed_truth
from photonpano.testing import corner_error_px


def _register(host, key, merged, options=None):
    need_backend(key)
    start = perturbed_truth() if key in DIRECT_LOCATORS else np.eye(3)
    config = host.registry("locator")[key](**(options or {}))
    return config.build().register_pairs(merged, np.array([[0, 1]]), start[None])


SLOW = {"kornia-sift", "pycolmap-sift"}  # 5-15 s each on the CI machine


@pytest.mark.parametrize("key", [pytest.param(k, marks=pytest.mark.slow) if k in SLOW else k for k in ALL_LOCATORS])
def test_recovers_the_real_warp_within_half_a_pixel(host, real_pair, key):
    result = _register(host, key, real_pair)
    assert result.ok[0]
    error = corner_error_px(result.homographies[0], H_TARGET_TO_SOURCE, 640, 480)
    assert error <= 0.5, f"{key}: mean corner error {error:.3f} px"
    # direction cross-check: the inverse warp is nowhere near
    assert corner_error_px(result.homographies[0], np.linalg.inv(H_TARGET_TO_SOURCE), 640, 480) > 50
    if key in DIRECT_LOCATORS:
        assert corner_error_px(perturbed_truth(), H_TARGET_TO_SOURCE, 640, 480) > 1.5  # it did improve
        assert result.matches[0] == 0 and result.inliers[0] > 100_000  # overlapping trusted pixels


@pytest.mark.slow
def test_pycolmap_without_polish_shows_the_pixel_convention_is_converted(host, real_pair):
    """COLMAP's own estimate, converted from its +0.5 pixel convention, is within 0.1 px.

    Left in COLMAP coordinates, the same estimate would be off by about (H - I)(0.5, 0.5),
    several tenths of a pixel at this scale.
    """
    from photonpano.plugins.locators.pycolmap_sift import from_colmap

    result = _register(host, "pycolmap-sift", real_pair, {"refine": "none"})
    h = result.homographies[0]
    assert corner_error_px(h, H_TARGET_TO_SOURCE, 640, 480) < 0.1
    # what an unconverted homography would have cost (h in COLMAP coordinates = inverse conversion)
    from photonpano import geometry

    unconverted = geometry.translation(0.5, 0.5) @ h @ geometry.translation(-0.5, -0.5)
    assert corner_error_px(unconverted, H_TARGET_TO_SOURCE, 640, 480) > 0.3
    np.testing.assert_allclose(from_colmap(unconverted), h / h[2, 2], atol=1e-9)


@pytest.mark.slow
def test_pycolmap_keypoints_follow_our_pixel_centres(host):
    """Keypoints of an image and of its exact 2x enlargement obey ``x_big = 2 x + 0.5``.

    That is the relation of pixel centres at integers; COLMAP's raw corner-origin
    keypoints would give ``2 x`` (measured: offset 0.500 px before conversion).
    """
    need_backend("pycolmap-sift")
    import cv2
    from locator_cases import DATA

    image = cv2.imread(str(DATA / "source.png"), cv2.IMREAD_GRAYSCALE)
    big = cv2.resize(image, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
    locator = host.registry("locator")["pycolmap-sift"](border_px=0).build()
    small_f = locator.describe(image, np.ones(image.shape, bool), None)
    big_f = locator.describe(big, np.ones(big.shape, bool), None)
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(small_f.descriptors.astype(np.float32),
                                                                big_f.descriptors.astype(np.float32))
    a = small_f.points[[m.queryIdx for m in matches]]
    b = big_f.points[[m.trainIdx for m in matches]]
    residual = b - 2 * a
    good = np.all(np.abs(residual - np.median(residual, 0)) < 1, axis=1)
    assert good.sum() > 1000
    np.testing.assert_allclose(np.median(residual[good], axis=0), [0.5, 0.5], atol=0.05)


def test_the_chains_locator_runs_ecc_to_where_it_ends(real_pair):
    """``OpenCVEccConfig.converging``: ECC to convergence, not to the mosaic's speed-tuned stopping rule.

    ECC stops when the correlation coefficient improves by less than ``epsilon``; the
    template defaults' 1e-4 stops the real pair 0.01 px short of where 300 iterations end
    (from the truth with the corners 1.6-2.6 px off), on the side of the start. The long
    chains' links, which measure a shape error of a few hundredths of a pixel per link,
    are registered with the converging config (photonpano.long_pairs).
    """
    from photonpano.plugins.locators.opencv_ecc import OpenCVEccConfig

    template = OpenCVEccConfig(**OpenCVEccConfig.template_defaults)
    converging = template.converging()
    assert (converging.iterations, converging.epsilon) == (10, 1e-8)
    assert OpenCVEccConfig(iterations=80).converging().iterations == 80  # a spec's longer run is kept
    start = perturbed_truth()[None]
    found = {name: config.build().register_pairs(real_pair, np.array([[0, 1]]), start).homographies[0]
             for name, config in (("template", template), ("converging", converging),
                                  ("end", template.model_copy(update={"iterations": 300, "epsilon": 1e-12})))}
    assert corner_error_px(found["converging"], found["end"], 640, 480) < 0.002
    assert corner_error_px(found["template"], found["end"], 640, 480) > 0.005
    assert corner_error_px(found["converging"], H_TARGET_TO_SOURCE, 640, 480) < 0.05
