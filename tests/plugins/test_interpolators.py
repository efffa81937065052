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


def test_shape_is_smoothed_harder_than_the_shift():
    """Noisy shape parameters of group means are smoothed by ``shape_smoothness``.

    The shape: rotation, scale, shear and perspective about the frame centre. The shift's
    fit is unchanged.
    """
    n, m = 20_000, 360
    refs = np.arange(0, n - m + 1, m // 2) + m // 2
    groups = Groups(start=refs - m // 2, stop=refs - m // 2 + m, reference=refs)
    truth = _path(np.arange(float(n)))
    means = np.stack([truth[a:b].mean(0) for a, b in zip(groups.start, groups.stop)])
    noise = np.random.default_rng(0).normal(0, 1, means.shape) * [2e-4, 2e-4, 2e-4, 2e-4, 0.03, 0.03, 4e-7, 4e-7]
    h = geometry.homographies_from_params(means + noise)
    corners = np.array([[-248.0, -127], [248, -127], [-248, 127], [248, 127]])  # about the frame centre

    def corner_rmse(config):
        out = config.build().interpolate(refs, h, n, groups)
        err = geometry.apply(out, corners) - geometry.apply(geometry.homographies_from_params(truth), corners)
        shift = geometry.params_from_homographies(out)[:, 4:6] - truth[:, 4:6]
        inner = slice(m, n - m)
        return (np.sqrt(np.mean(np.sum(err[inner] ** 2, -1))), np.sqrt(np.mean(np.sum(shift[inner] ** 2, -1))))

    default, same = corner_rmse(CubicLKConfig()), corner_rmse(CubicLKConfig(shape_smoothness=1e-3))
    assert default[0] < 0.7 * same[0], (default, same)  # measured: 0.085 against 0.149 px
    assert default[1] == pytest.approx(same[1])  # the shift's fit is the same
    assert default[1] < 0.1  # the noise of 0.03 px per group, not a bias


def test_keyframes_whose_shape_a_passing_object_pulled_do_not_bend_their_neighbours():
    """Three consecutive keyframes with a turned shape (a mover pulled them) barely bend the fit.

    The Huber fit keeps the smoothed shape around them near the path; plain least squares
    spreads their error over the stretch the shape's smoothness couples.
    """
    n, m = 20_000, 360
    refs = np.arange(0, n - m + 1, m // 2) + m // 2
    groups = Groups(start=refs - m // 2, stop=refs - m // 2 + m, reference=refs)
    truth = _path(np.arange(float(n)))
    means = np.stack([truth[a:b].mean(0) for a, b in zip(groups.start, groups.stop)])
    means += np.random.default_rng(1).normal(0, 1, means.shape) * [2e-5, 2e-5, 2e-5, 2e-5, 0.03, 0.03, 4e-8, 4e-8]
    pulled = means.copy()
    pulled[50:53, 0] += 4e-3  # 1 px at 250 px from the frame centre

    def error_near_the_pull(config):
        h = geometry.homographies_from_params(pulled)
        out = geometry.params_from_homographies(config.build().interpolate(refs, h, n, groups))
        near = slice(refs[40], refs[63])
        return np.abs(out[near, 0] - truth[near, 0]).max() * 250

    robust, plain = error_near_the_pull(CubicLKConfig()), error_near_the_pull(CubicLKConfig(outlier_threshold=None))
    assert robust < 0.6 * plain, (robust, plain)  # measured: 0.50 against 0.99 px
