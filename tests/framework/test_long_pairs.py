"""Held-out chains of registrations far apart: the shape error neighbouring frames share."""

import numpy as np
from photonpano import geometry
from photonpano.long_pairs import (
    CHAINS,
    LINK_EXTENT,
    MAX_LINK_FRACTION,
    chain_shape_error,
    correct_shape_drift,
    long_baseline_chains,
)
from photonpano.metrics import trajectory_error
from photonpano.records import Groups, LevelResult, LocateResult, PairRegistrations
from photonpano.uncertainty import frame_extents_travelled, frame_uncertainty

W, H = 248, 128
N_FRAMES, M = 20_000, 200


def _groups():
    """Groups of M frames every M / 2, with the short anchor groups at both ends (as ``midpoint``)."""
    ref = np.concatenate([[0], np.arange(M // 2, N_FRAMES - M // 2 + 1, M // 2), [N_FRAMES - 1]])
    start = np.maximum(ref - M // 2, 0)
    stop = np.minimum(ref + M // 2, N_FRAMES)
    start[0], stop[0], start[-1], stop[-1] = 0, 10, N_FRAMES - 10, N_FRAMES
    return Groups(start=start, stop=stop, reference=ref)


def _pan(speed=0.005):
    """(T, 3, 3) a pan at ``speed`` px/frame (100 px over the capture)."""
    return np.stack([geometry.translation(speed * t, 0.0) for t in range(N_FRAMES)])


def _sheared(homographies, peak):
    """The homographies with a shear ramp (y moved by x) from -peak to +peak px at the frame corner."""
    ramp = np.linspace(-1.0, 1.0, len(homographies)) * peak / (W / 2)
    shear = np.repeat(np.eye(3)[None], len(homographies), axis=0)
    shear[:, 1, 0] = ramp
    return homographies @ geometry.from_centre(shear, W, H)


def _chains_registered(truth, groups, noise_px, seed=0):
    """The chains of the current estimate ``truth`` and their registrations: the truth plus noise."""
    links = long_baseline_chains(truth[groups.reference], groups.stop - groups.start, W, H)
    rng = np.random.default_rng(seed)
    ref = groups.reference
    relative = np.linalg.inv(truth[ref[links[:, 1]]]) @ truth[ref[links[:, 2]]]
    noise = np.repeat(np.eye(3)[None], len(links), axis=0)
    noise[:, :2, 2] = rng.normal(0, noise_px, (len(links), 2))
    noise[:, 1, 0] = rng.normal(0, noise_px / (W / 2), len(links))  # a rotation-like term, seen at the corners
    return links, geometry.normalize(noise @ relative)


def test_chains_run_from_the_first_full_group_to_the_last_in_links_that_overlap_well():
    groups = _groups()
    truth = _pan(speed=0.02)  # 400 px over the capture: the frames' overlap limits the links
    links = long_baseline_chains(truth[groups.reference], groups.stop - groups.start, W, H)
    g = len(groups.reference)
    assert set(links[:, 0]) == set(range(CHAINS))
    for m in range(CHAINS):
        mine = links[links[:, 0] == m]
        assert mine[0, 1] == 1 and mine[-1, 2] == g - 2  # the short anchor groups are left out
        assert (mine[1:, 1] == mine[:-1, 2]).all() and (mine[:, 2] > mine[:, 1]).all()
        travelled = np.abs(0.02 * (groups.reference[mine[:, 2]] - groups.reference[mine[:, 1]]))
        assert (travelled <= LINK_EXTENT * W + 1e-9).all()
        assert (mine[:, 2] - mine[:, 1] <= MAX_LINK_FRACTION * g).all()
    first = [int(np.diff(links[links[:, 0] == m][0, 1:])[0]) for m in range(CHAINS)]
    assert first[1] < first[2] < first[3] < first[0]  # the chains' links fall on different groups
    assert len(long_baseline_chains(truth[:7], np.full(7, M), W, H)) == 0


def test_a_shear_ramp_is_recovered_and_noise_alone_is_taken_off():
    groups = _groups()
    truth = _pan()
    estimate = _sheared(truth, peak=0.3)  # a ramp of 0.3 px at the corners at either end
    actual = trajectory_error(estimate, truth, W, H).per_frame_px
    links, registered = _chains_registered(truth, groups, noise_px=0.05)
    ok = np.ones(len(links), bool)
    shape, unresolved = chain_shape_error(registered, ok, links, groups.reference, estimate, W, H)
    inner = slice(groups.reference[1], groups.reference[-2])
    assert 0.75 < np.sqrt(np.mean(shape[inner] ** 2)) / np.sqrt(np.mean(actual[inner] ** 2)) < 1.25
    assert shape[100] > 2 * shape[N_FRAMES // 2]  # larger at the ends than in the middle, as the ramp
    # the right trajectory: what is left of the links' noise once the chains' spread is taken off
    # (four noise draws: 0.019 px on average, 0.033 with the spread left in)
    left = [chain_shape_error(_chains_registered(truth, groups, noise_px=0.05, seed=seed)[1], ok, links,
                              groups.reference, truth, W, H)[0] for seed in range(4)]
    assert np.mean([np.sqrt(np.mean(x ** 2)) for x in left]) < 0.025
    broken = ok & (np.arange(len(ok)) != 3)  # a failed link (of chain 0) leaves its chain out
    without_one = chain_shape_error(registered, broken, links, groups.reference, estimate, W, H)
    assert without_one is not None and np.abs(without_one[0] - shape).max() < 0.1
    assert 0 < unresolved.min() and unresolved.max() < 0.1  # the chains' standard error, of 0.05 px links
    one_left = links[:, 0] == 5
    assert chain_shape_error(registered, one_left, links, groups.reference, estimate, W, H) is None


def _last_level(groups, truth, estimate, links=None, registered=None):
    """A mosaic level that found ``estimate``: its held-out pairs the truth, its chains ``registered``."""
    ref = groups.reference
    g = len(ref)
    index = np.stack([np.arange(g - 1), np.arange(1, g)], axis=1)
    consecutive = np.linalg.inv(truth[ref[:-1]]) @ truth[ref[1:]]
    cross = PairRegistrations(consecutive, np.zeros(g - 1, np.int64), np.zeros(g - 1, np.int64), np.ones(g - 1, bool))
    regs = PairRegistrations(np.repeat(np.eye(3)[None], g, 0), np.zeros(g, np.int64), np.zeros(g, np.int64),
                             np.ones(g, bool))
    chain = None if links is None else PairRegistrations(registered, np.zeros(len(links), np.int64),
                                                         np.zeros(len(links), np.int64), np.ones(len(links), bool))
    return LevelResult(3, "mosaic", groups, LocateResult(estimate[ref], regs, None, crosscheck=cross,
                                                         crosscheck_index=index, chain=chain, chain_index=links),
                       estimate)


def test_the_shape_term_raises_the_predicted_sigma_where_the_consecutive_pairs_see_nothing():
    groups = _groups()
    truth = _pan()
    estimate = _sheared(truth, peak=0.3)  # the ramp changes by 0.003 px per consecutive pair
    links, registered = _chains_registered(truth, groups, noise_px=0.02)
    actual = trajectory_error(estimate, truth, W, H).per_frame_px
    before, after = (frame_uncertainty(level, W, H) for level in (_last_level(groups, truth, estimate),
                                                                   _last_level(groups, truth, estimate, links,
                                                                               registered)))
    assert np.mean(actual < 2 * before.sigma_px) < 0.6
    assert np.mean(actual < 2 * after.sigma_px) > 0.9
    assert before.shape_links == 0 and after.shape_links == len(links)
    summary = after.summary(1000.0)
    assert summary["shape_links"] == len(links) and 0.2 < summary["shape_max_px"] < 0.45
    assert after.shape_px is not None and before.shape_px is None
    # every frame overlaps the middle one by more than half: nothing unresolved is added
    resolved, unresolved = chain_shape_error(registered, np.ones(len(links), bool), links, groups.reference,
                                             estimate, W, H)
    assert np.array_equal(after.shape_px, resolved) and unresolved.max() > 0


def test_the_shape_drift_the_chains_agree_on_is_taken_out_and_their_noise_alone_moves_little():
    """A shear ramp of 0.3 px is mostly taken out; on the right trajectory the links' noise moves no frame."""
    groups = _groups()
    truth = _pan()
    estimate = _sheared(truth, peak=0.3)
    links, registered = _chains_registered(truth, groups, noise_px=0.05)
    ok = np.ones(len(links), bool)
    before = trajectory_error(estimate, truth, W, H).rmse_px
    corrected, moved = correct_shape_drift(registered, ok, links, groups.reference, estimate, W, H)
    after = trajectory_error(corrected, truth, W, H).rmse_px
    assert after < 0.4 * before and 0.15 < moved < 0.4, (before, after, moved)  # 0.173 -> 0.030-0.057 px (4 draws)
    kept, moved = correct_shape_drift(registered, ok, links, groups.reference, truth, W, H)
    assert trajectory_error(kept, truth, W, H).rmse_px < 0.02 and moved < 0.03
    one_left = links[:, 0] == 5
    same, moved = correct_shape_drift(registered, one_left, links, groups.reference, estimate, W, H)
    assert moved == 0.0 and np.array_equal(same, estimate)


def test_a_ramp_the_chains_see_at_only_4_standard_errors_is_taken_out_too():
    """A 0.2 px shear ramp under links of 0.1 px noise: 3.5-5 standard errors (four noise draws).

    At ``DRIFT_SIGNIFICANCE`` 6 it stayed (0.115 px); at 3 it goes to 0.045-0.085 px.
    """
    groups = _groups()
    truth = _pan()
    estimate = _sheared(truth, peak=0.2)
    before = trajectory_error(estimate, truth, W, H).rmse_px
    after = []
    for seed in range(4):
        links, registered = _chains_registered(truth, groups, noise_px=0.1, seed=seed)
        corrected, _ = correct_shape_drift(registered, np.ones(len(links), bool), links, groups.reference,
                                           estimate, W, H)
        after.append(trajectory_error(corrected, truth, W, H).rmse_px)
    assert max(after) < 0.85 * before and np.mean(after) < 0.65 * before, (before, after)


def test_a_link_registered_both_ways_keeps_their_mean_and_cancels_a_bias_that_follows_the_warped_frame():
    """``links_both_ways``: a bias of +b one way and -b the other leaves the true change; ok needs both ways."""
    from photonpano.long_pairs import links_both_ways, register_links

    rng = np.random.default_rng(0)
    expected = np.stack([geometry.translation(60.0 + k, 2.0) for k in range(5)])
    true_change = rng.normal(0, 1e-3, (5, 8)) * [1, 1, 1, 1, 100, 100, 1e-3, 1e-3]
    bias = np.array([4e-3, 0, 0, 0, 0.2, 0, 0, 0])  # a horizontal scale and shift that follow the warped frame

    def registered(params):
        return expected @ geometry.from_centre(geometry.homographies_from_params(params), W, H)

    ok = np.array([True, True, False, True, True])
    forward = PairRegistrations(registered(true_change + bias), np.zeros(5, np.int64), np.zeros(5, np.int64), ok)
    backward = PairRegistrations(registered(true_change - bias), np.zeros(5, np.int64), np.zeros(5, np.int64),
                                 np.ones(5, bool))
    mean = links_both_ways(forward, backward, expected, W, H)
    error = geometry.mean_corner_distance(mean.homographies, registered(true_change), W, H)
    assert error.max() < 1e-3, error  # second order in the change
    assert geometry.mean_corner_distance(forward.homographies, registered(true_change), W, H).min() > 0.2
    np.testing.assert_array_equal(mean.ok, ok)

    class Recorder:
        def register_pairs(self, merged, pairs, initial, context):
            self.pairs, self.initial = pairs, initial
            return PairRegistrations(initial @ geometry.translation(0.5, 0.0), np.zeros(len(pairs), np.int64),
                                     np.zeros(len(pairs), np.int64), np.ones(len(pairs), bool))

    locator, pairs = Recorder(), np.array([[0, 1], [1, 2]])
    back = register_links(locator, None, pairs, expected[:2], backward=True)
    np.testing.assert_array_equal(locator.pairs, pairs[:, ::-1])
    np.testing.assert_allclose(locator.initial, np.linalg.inv(expected[:2]))
    np.testing.assert_allclose(back.homographies, geometry.translation(-0.5, 0.0) @ expected[:2], atol=1e-12)


def test_the_frame_means_in_closed_form_are_those_over_every_frame():
    """The drift correction's means over the frames, from the chains' nodes only, equal those over every frame."""
    from photonpano.long_pairs import _frame_sums, _interpolate

    rng = np.random.default_rng(3)
    nodes = np.unique(rng.integers(0, 5_000, 40)).astype(np.float64)
    values = rng.normal(size=(3, len(nodes), 8))
    every = _interpolate(np.arange(nodes[0], nodes[-1] + 1), nodes, values)  # (3, F, 8)
    linear, diag, off = _frame_sums(nodes)
    assert linear.sum() == every.shape[1]
    np.testing.assert_allclose(np.einsum("n,mnk->mk", linear, values), every.sum(axis=1), rtol=1e-10)
    squares = (np.einsum("n,mnk->mk", diag, values ** 2)
               + 2 * np.einsum("n,mnk->mk", off, values[:, :-1] * values[:, 1:]))
    np.testing.assert_allclose(squares, (every ** 2).sum(axis=1), rtol=1e-10)
    frames = np.arange(nodes[0] - 50, nodes[-1] + 50)  # the interpolation is numpy's, constant beyond the nodes
    interpolated = _interpolate(frames, nodes, values)
    for k in range(8):
        np.testing.assert_allclose(interpolated[1, :, k], np.interp(frames, nodes, values[1, :, k]))


def test_the_size_of_an_error_is_its_mean_corner_distance_about_the_centre():
    """``_size`` (elementwise, for 8 chains x 100 000 frames) is the 3x3 route's mean corner distance."""
    from photonpano.long_pairs import _size

    rng = np.random.default_rng(3)
    params = rng.normal(0.0, 1e-3, (2, 50, 8)) * np.array([1, 1, 1, 1, 300, 300, 1e-3, 1e-3])
    moved = geometry.from_centre(geometry.homographies_from_params(params), W, H)
    expected = geometry.mean_corner_distance(moved, np.broadcast_to(np.eye(3), moved.shape), W, H)
    np.testing.assert_allclose(_size(params, W, H), expected, rtol=1e-9, atol=1e-12)
    assert _size(params, W, H).shape == (2, 50)


def test_the_level_change_fits_its_alignment_on_spaced_frames_and_measures_every_frame():
    """``uncertainty.level_change`` (alignment fitted on 5 000 of 20 000 frames) as fitted on all, within 2e-5 px."""
    import pytest
    from photonpano.uncertainty import level_change

    truth = _pan()
    estimated = _sheared(truth, 0.5) @ geometry.translation(3.0, -2.0)
    on_all = trajectory_error(estimated, truth, W, H)
    assert on_all.rmse_px > 0.1  # the shear ramp is not removed by any global alignment
    expected = np.maximum(geometry.mean_corner_distance(estimated, truth, W, H), on_all.per_frame_px)
    np.testing.assert_allclose(level_change(estimated, truth, W, H), expected, atol=2e-5)
    with pytest.raises(ValueError, match="differ"):
        level_change(estimated, truth[:-1], W, H)


def test_a_fast_pan_keeps_the_shape_error_its_chains_cannot_resolve():
    """A shear ramp of 0.3 px under chains whose links are 0.3 px noisy: within twice the sigma where it was not."""
    groups = _groups()
    truth = _pan(speed=0.03)  # 600 px: the ends lie 1.2 frame widths from the middle frame
    estimate = _sheared(truth, peak=0.3)
    actual = trajectory_error(estimate, truth, W, H).per_frame_px
    assert frame_extents_travelled(estimate, W, H).max() > 1
    within, within_resolved = [], []
    for seed in range(3):
        links, registered = _chains_registered(truth, groups, noise_px=0.3, seed=seed)
        resolved, unresolved = chain_shape_error(registered, np.ones(len(links), bool), links, groups.reference,
                                                 estimate, W, H)
        found = frame_uncertainty(_last_level(groups, truth, estimate, links, registered), W, H)
        assert (found.shape_px >= unresolved - 1e-12).all()  # all of it: the ends no longer overlap the middle
        within.append(np.mean(actual <= 2 * found.sigma_px))
        without = np.sqrt(found.sigma_px ** 2 - found.shape_px ** 2 + resolved ** 2)  # the resolved part alone
        within_resolved.append(np.mean(actual <= 2 * without))
    assert min(within) > 0.9 and np.mean(within_resolved) < 0.5, (within, within_resolved)
