import numpy as np
import pytest
from photonpano import geometry
from photonpano.plugins.interpolators.cubic_lk import CubicLKConfig
from photonpano.stages import Groups


def _path(t):
    """A smooth trajectory: pan plus a 30 Hz vibration at 100 kHz, slight zoom."""
    p = np.zeros((len(t), 8))
    p[:, 4] = 0.02 * t + 5 * np.sin(2 * np.pi * 30 * t / 1e5)
    p[:, 5] = 5 * np.cos(2 * np.pi * 30 * t / 1e5)
    p[:, 0] = p[:, 3] = 1e-6 * t
    return p


def test_reference_frame_mode_passes_through_keyframes_and_extrapolates():
    keys = np.arange(250, 10_000, 250)
    h = geometry.homographies_from_params(_path(keys.astype(float)))
    out = CubicLKConfig(measurement="reference-frame").build().interpolate(keys, h, 10_000)
    assert out.shape == (10_000, 3, 3) and out.dtype == np.float64
    np.testing.assert_allclose(out[keys], h, atol=1e-9)
    truth = _path(np.arange(10_000.0))
    err = np.abs(geometry.params_from_homographies(out) - truth)[:, 4:6]
    assert err[keys[0]:keys[-1]].max() < 0.01  # between keyframes: cubic accuracy
    assert err.max() < 0.5  # 250 frames of linear extrapolation at each end


def test_exposure_average_mode_recovers_the_path_from_group_means():
    n, m = 10_000, 500
    refs = np.arange(0, n - m + 1, 125) + m // 2
    groups = Groups(start=refs - m // 2, stop=refs - m // 2 + m, reference=refs)
    truth = _path(np.arange(float(n)))
    means = np.stack([truth[a:b].mean(0) for a, b in zip(groups.start, groups.stop)])
    h = geometry.homographies_from_params(means)
    out = CubicLKConfig().build().interpolate(refs, h, n, groups)
    err = np.linalg.norm(geometry.params_from_homographies(out)[:, 4:6] - truth[:, 4:6], axis=1)
    # interpolating the means as if they were instants would be off by ~0.1 px (box blur of the vibration)
    naive = CubicLKConfig(measurement="reference-frame").build().interpolate(refs, h, n)
    naive_err = np.linalg.norm(geometry.params_from_homographies(naive)[:, 4:6] - truth[:, 4:6], axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.02
    assert np.sqrt(np.mean(naive_err[m:-m] ** 2)) > 3 * np.sqrt(np.mean(err[m:-m] ** 2))


def test_one_and_two_keyframes_and_bad_input():
    interp = CubicLKConfig(measurement="reference-frame").build()
    one = interp.interpolate(np.array([5]), geometry.translation(2, 3)[None], 10)
    np.testing.assert_allclose(one, np.repeat(geometry.translation(2, 3)[None], 10, 0))
    two = interp.interpolate(np.array([0, 10]), np.stack([np.eye(3), geometry.translation(10, 0)]), 21)
    np.testing.assert_allclose(two[20], geometry.translation(20, 0))  # linear extrapolation
    with pytest.raises(ValueError):
        interp.interpolate(np.array([3, 3]), np.stack([np.eye(3)] * 2), 10)
