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


def _noisy_group_means(truth, n, m, seed, noise=(2e-4, 2e-4, 2e-4, 2e-4, 0.03, 0.03, 4e-7, 4e-7)):
    """Groups of m frames every m/4 frames, and their mean parameters with registration noise."""
    refs = np.arange(0, n - m + 1, m // 4) + m // 2
    groups = Groups(start=refs - m // 2, stop=refs - m // 2 + m, reference=refs)
    means = np.stack([truth[a:b].mean(0) for a, b in zip(groups.start, groups.stop)])
    return groups, means + np.random.default_rng(seed).normal(0, 1, means.shape) * noise


def _corner_and_shift_rmse(config, groups, means, truth, n, m):
    """RMS corner error (px) and shift error (px) of a fit, away from the ends."""
    corners = np.array([[-248.0, -127], [248, -127], [-248, 127], [248, 127]])  # about the frame centre
    out = config.build().interpolate(groups.reference, geometry.homographies_from_params(means), n, groups)
    err = geometry.apply(out, corners) - geometry.apply(geometry.homographies_from_params(truth), corners)
    shift = geometry.params_from_homographies(out)[:, 4:6] - truth[:, 4:6]
    inner = slice(m, n - m)
    return np.sqrt(np.mean(np.sum(err[inner] ** 2, -1))), np.sqrt(np.mean(np.sum(shift[inner] ** 2, -1)))


def test_a_pans_constant_shape_gets_a_stiff_spline():
    """``shape_smoothness: auto`` smooths the noisy shape of a pan (rotation, scale, shear, perspective) hard.

    The shift's fit does not depend on it. (Noise on the shape only, so that the corner
    error is the shape's.)
    """
    n, m = 20_000, 360
    truth = _path(np.arange(float(n)))
    groups, means = _noisy_group_means(truth, n, m, seed=0, noise=(2e-4, 2e-4, 2e-4, 2e-4, 0, 0, 4e-7, 4e-7))
    auto = _corner_and_shift_rmse(CubicLKConfig(), groups, means, truth, n, m)
    supple = _corner_and_shift_rmse(CubicLKConfig(shape_smoothness=1.0), groups, means, truth, n, m)
    assert auto[0] < 0.5 * supple[0], (auto, supple)  # measured: 0.007 against 0.038 px
    assert auto[1] == pytest.approx(supple[1])  # the shift's fit is the same


def test_a_camera_that_rolls_fast_keeps_its_roll():
    """A 2 degree roll at 30 Hz: cross-validation keeps the shape supple enough to follow it."""
    n, m = 20_000, 360
    t = np.arange(float(n))
    truth = _path(t)
    angle = np.deg2rad(2.0) * np.sin(2 * np.pi * 30 * t / 1e5)
    truth[:, 0] = truth[:, 3] = np.cos(angle) - 1
    truth[:, 1], truth[:, 2] = np.sin(angle), -np.sin(angle)
    groups, means = _noisy_group_means(truth, n, m, seed=1)
    auto = _corner_and_shift_rmse(CubicLKConfig(), groups, means, truth, n, m)[0]
    supple = _corner_and_shift_rmse(CubicLKConfig(shape_smoothness=1e-3), groups, means, truth, n, m)[0]
    stiff = _corner_and_shift_rmse(CubicLKConfig(shape_smoothness=1e4), groups, means, truth, n, m)[0]
    assert auto < 1.2 * supple and auto < 0.2 * stiff, (auto, supple, stiff)  # measured: 0.093, 0.109, 6.57 px


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


def test_the_exposure_design_is_banded_and_holds_the_group_means_of_the_basis():
    """Each row is zero outside the basis functions its group meets, and the group means of the basis inside.

    Overlapping groups over 20 000 frames give a band of at most 8 (the rounding of two equal integrals
    had spread every row over all 121 basis functions).
    """
    from photonpano.plugins.interpolators.cubic_lk import exposure_design
    from scipy.interpolate import BSpline

    n, m = 20_000, 340
    refs = np.arange(m // 2, n - m // 2, m // 4)  # a third level's overlapping groups
    groups = Groups(start=refs - m // 2, stop=refs - m // 2 + m, reference=refs)
    knots, design = exposure_design(groups, n)
    assert design.n_basis > 100 and design.width <= 8
    dense = np.zeros((len(groups), design.n_basis))
    np.put_along_axis(dense, design.first[:, None] + np.arange(design.width), design.values, axis=1)
    integral = BSpline(knots, np.eye(design.n_basis), 3).antiderivative()
    means = (integral(groups.stop - 0.5) - integral(groups.start - 0.5)) / m
    np.testing.assert_allclose(dense, means, rtol=0, atol=1e-12)
