"""The joint bilateral sums of the luminance-guided colour's fine ratio."""

import numpy as np
import pytest
from photonpano.plugins.compositors._bilateral import joint_bilateral_sums


def _gaussian_sums(image, sigma_px):
    """Truncated-Gaussian sums (radius ceil(2 sigma), zeros outside), written out."""
    radius = int(np.ceil(2 * sigma_px))
    h, w = image.shape
    padded = np.pad(image.astype(np.float64), radius)
    out = np.zeros((h, w))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            out += np.exp(-(dx * dx + dy * dy) / (2 * sigma_px ** 2)) * padded[radius + dy:radius + dy + h,
                                                                              radius + dx:radius + dx + w]
    return out


def test_joint_bilateral_sums_are_gaussian_sums_on_a_flat_guide_and_stop_at_an_edge():
    rng = np.random.default_rng(1)
    values = rng.random((2, 24, 40)).astype(np.float32)
    flat = np.zeros((24, 40), np.float32)
    sums, squared = joint_bilateral_sums(values, values[:1], flat, 1.5, 0.3)
    np.testing.assert_allclose(sums[0], _gaussian_sums(values[0], 1.5), rtol=1e-5)
    np.testing.assert_allclose(sums[1], _gaussian_sums(values[1], 1.5), rtol=1e-5)
    # the squared weights: a Gaussian of sigma / sqrt(2)
    np.testing.assert_allclose(squared[0], _gaussian_sums(values[0], 1.5 / np.sqrt(2)), rtol=1e-5, atol=1e-6)
    # a step of the guide by 1 (e.g. log luminance: a factor e) at column 20: nothing crosses it
    step = np.where(np.arange(40) < 20, 0, 1).astype(np.float32)[None].repeat(24, 0)
    right = np.zeros((1, 24, 40), np.float32)
    right[0, :, 20:] = 1
    crossed, _ = joint_bilateral_sums(right, right, step, 1.5, 0.1)
    assert crossed[0, :, :20].max() < 1e-6 * crossed[0, :, 20:].max()
    # a NaN guide pixel contributes nothing; a NaN centre gets the plain Gaussian
    holes = flat.copy()
    holes[10, 10] = np.nan
    around, _ = joint_bilateral_sums(np.ones((1, 24, 40), np.float32), np.ones((1, 24, 40), np.float32), holes,
                                     1.5, 0.3)
    full = _gaussian_sums(np.ones((24, 40)), 1.5)
    assert around[0, 10, 11] == pytest.approx(full[10, 11] - np.exp(-1 / 4.5), rel=1e-5)
    assert around[0, 10, 10] == pytest.approx(full[10, 10] - 1, rel=1e-5)
    with pytest.raises(ValueError, match="joint_bilateral_sums: expected"):
        joint_bilateral_sums(values[0], values, flat, 1.5, 0.3)
    with pytest.raises(ValueError, match="range_sigma"):
        joint_bilateral_sums(values, values, flat, 1.5, 0)

