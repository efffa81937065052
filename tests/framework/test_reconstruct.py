"""The pose graph, its outlier handling and the guards, on synthetic registrations."""

import numpy as np
import pytest
from photonpano import geometry
from photonpano.errors import StageError
from photonpano.guards import agrees_with_neighbours, guard_keyframes, plausible
from photonpano.posegraph import chain_keyframes, pairs_at_offsets
from photonpano.schemes import locate_keyframes
from photonpano.stages import Locator, MergedFrames, PairRegistrations

W, H = 200, 100


def _truth(g):
    t = np.arange(g)
    return np.array([geometry.translation(3.0 * k + 2 * np.sin(k / 3), np.cos(k / 5)) for k in t])


class NoisyLocator(Locator):
    """Returns the true pair homographies plus corner noise; chosen pairs are wrong."""

    def __init__(self, truth, noise_px, wrong=(), seed=0):
        self.truth, self.noise, self.wrong = truth, noise_px, set(wrong)
        self.rng = np.random.default_rng(seed)

    def _register_pairs(self, merged, pairs, initial, context):
        out = []
        for a, b in merged.flux[pairs, 0, 0].astype(int):  # the frames carry their group index
            rel = np.linalg.inv(self.truth[a]) @ self.truth[b]
            c = geometry.corners(W, H)
            moved = geometry.apply(rel, c) + self.rng.normal(scale=self.noise, size=(4, 2))
            if (a, b) in self.wrong:
                moved += 15.0  # plausible but 15 px off
            import cv2
            out.append(cv2.getPerspectiveTransform(c.astype(np.float32), moved.astype(np.float32)))
        p = len(pairs)
        return PairRegistrations(np.array(out).reshape(p, 3, 3), np.full(p, 100), np.full(p, 100), np.ones(p, bool))


def _numbered(index):
    """Merged frames of 1x1 pixel whose flux is the group index (what NoisyLocator reads)."""
    k = len(index)
    return MergedFrames(index.astype(np.float32).reshape(k, 1, 1), np.ones((k, 1, 1), np.float32),
                        np.zeros((k, 1, 1), np.uint8), np.ones((k, 1, 1), bool))


def _error(estimate, truth):
    from photonpano.metrics import trajectory_error
    return trajectory_error(estimate, truth, W, H).rmse_px


def test_longer_pairs_remove_chaining_drift():
    truth = _truth(80)
    start = np.repeat(np.eye(3)[None], 80, 0)
    chain, _, _ = locate_keyframes(NoisyLocator(truth, 0.3), _numbered, start, (1,), W, H)
    graph, _, _ = locate_keyframes(NoisyLocator(truth, 0.3), _numbered, start, (1, 2, 4, 8, 16, 32), W, H)
    assert _error(graph, truth) < 0.5 * _error(chain, truth)


def test_a_wrong_consecutive_link_is_outvoted():
    truth = _truth(40)
    start = np.repeat(np.eye(3)[None], 40, 0)
    loc = NoisyLocator(truth, 0.05, wrong={(10, 11)})
    solved, index, pairs = locate_keyframes(loc, _numbered, start, (1, 2, 4, 8), W, H)
    assert _error(solved, truth) < 0.2
    wrong = np.flatnonzero((index[:, 0] == 10) & (index[:, 1] == 11))[0]
    assert not pairs.ok[wrong]


def test_chain_bridges_failed_pairs_and_fails_when_all_fail():
    truth = _truth(6)
    rel = np.linalg.inv(truth[:-1]) @ truth[1:]
    ok = np.array([True, False, True, True, True])
    pairs = PairRegistrations(np.where(ok[:, None, None], rel, np.eye(3)), np.zeros(5, np.int64),
                              np.zeros(5, np.int64), ok)
    keys = chain_keyframes(truth[:1].repeat(6, 0), pairs)
    # the bridged step is interpolated from its neighbours: close to the true pan of ~3 px
    assert _error(keys, truth) < 1.0
    with pytest.raises(StageError, match="all 5 pairs"):
        chain_keyframes(truth, PairRegistrations(rel, np.zeros(5, np.int64), np.zeros(5, np.int64), np.zeros(5, bool)))


def test_plausible_flags_folds_and_rescaling():
    fold = np.diag([-1.0, 1.0, 1.0])
    shrink = np.diag([0.3, 0.3, 1.0])
    tilt = np.array([[1, 0, 0], [0, 1, 0], [0.02, 0, 1.0]])  # the horizon crosses the frame
    ok = plausible(np.stack([np.eye(3), geometry.translation(50, 5), fold, shrink, tilt]), W, H)
    np.testing.assert_array_equal(ok, [True, True, False, False, False])


def _turning(yaw_deg):
    """(G, 3, 3) homographies of a pinhole camera (f = W) turned by each yaw, about the frame centre."""
    f, c = float(W), geometry.translation((W - 1) / 2, (H - 1) / 2)
    k = np.diag([f, f, 1.0])
    out = []
    for a in np.deg2rad(yaw_deg):
        turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        out.append(c @ k @ turn @ np.linalg.inv(k) @ np.linalg.inv(c))
    return geometry.normalize(np.stack(out))


def test_a_turning_pan_keeps_its_keyframes_and_an_outlier_among_them_is_replaced():
    """Level 1's update is the whole pose: a 50-degree pan rescales its ends 2x and more, each step very little.

    The area bound of plausible() alone rejected the turned keyframes and bridged them from
    the middle ones (a 400 px tripod pan of the city: 68 px after level 1, 0.44 px since).
    """
    keyframes = _turning(np.linspace(-25, 25, 21))
    keyframes = geometry.normalize(np.linalg.inv(keyframes[0]) @ keyframes)  # the pose graph's gauge: the first
    identity = np.repeat(np.eye(3)[None], len(keyframes), axis=0)
    assert not plausible(keyframes, W, H).all()  # the ends, against the identity
    assert agrees_with_neighbours(keyframes, W, H).all()
    kept, rejected = guard_keyframes(identity, keyframes, W, H)
    assert rejected == 0 and np.array_equal(kept, keyframes)
    wild = keyframes.copy()
    wild[7] = wild[7] @ np.diag([0.3, 0.3, 1.0])  # a degenerate solve
    fixed, rejected = guard_keyframes(identity, wild, W, H)
    assert rejected == 1
    corners = geometry.corners(W, H)
    off = np.abs(geometry.apply(fixed[7], corners) - geometry.apply(keyframes[7], corners)).max()
    assert off < 2.0  # bridged from its neighbours, close to the truth (the keyframes are 2.5 degrees apart)
    np.testing.assert_array_equal(agrees_with_neighbours(wild, W, H)[5:10], [True, True, False, True, True])
    assert agrees_with_neighbours(keyframes[:2], W, H).all()
    assert not agrees_with_neighbours(keyframes[:1], W, H).any()


def test_pairs_at_offsets():
    np.testing.assert_array_equal(pairs_at_offsets(4, (2,)), [[0, 1], [1, 2], [2, 3], [0, 2], [1, 3]])


def test_merged_frames_stream_through_a_bounded_window():
    """Each group is merged once and the locator never sees more than window + max offset frames."""
    truth = _truth(100)
    merged_groups, seen = [], []

    def merge(index):
        merged_groups.extend(index.tolist())
        return _numbered(index)

    class Recording(NoisyLocator):
        def _register_pairs(self, merged, pairs, initial, context):
            seen.append(len(merged))
            return super()._register_pairs(merged, pairs, initial, context)

    solved, index, _ = locate_keyframes(Recording(truth, 0.05), merge, truth[:1].repeat(100, 0), (1, 2, 8), W, H,
                                        window=10)
    assert merged_groups == list(range(100))
    assert max(seen) == 2 * 10 + 8
    assert {8} <= set((index[:, 1] - index[:, 0]).tolist()) <= {1, 2, 8}
    assert _error(solved, truth) < 0.2
