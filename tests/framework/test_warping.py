import numpy as np
from photonpano import geometry
from photonpano.warping import WarpAccumulator, subbatch_edges


def test_subbatch_edges_bound_the_corner_travel():
    shifts = np.cumsum(np.full(200, 0.03))
    h = np.array([geometry.translation(s, 0) for s in shifts])
    edges = subbatch_edges(h, 40, 30, 0.25)
    assert edges[0] == 0 and edges[-1] == 200
    for a, b in zip(edges[:-1], edges[1:]):
        assert shifts[b - 1] - shifts[a] < 0.25
    assert len(edges) - 1 <= 200 * 0.03 / 0.25 + 2  # not one warp per frame


def test_accumulator_integer_shift_is_exact_and_clipped():
    acc = WarpAccumulator(10, 12)
    counts = np.arange(20, dtype=np.float32).reshape(4, 5)
    acc.add(counts, 3, geometry.translation(9, 2))  # partly outside the canvas
    np.testing.assert_array_equal(acc.counts[2:6, 9:12], counts[:, :3])
    np.testing.assert_array_equal(acc.frames[2:6, 9:12], 3)
    assert acc.counts.sum() == counts[:, :3].sum()
    acc.add(counts, 1, geometry.translation(100, 100))  # fully outside: ignored
    assert acc.frames.sum() == 3 * 12


def test_accumulator_footprints_kinds_and_degenerate_warps():
    """The compiled footprint pass: identity adds in place, perspective stays perspective, bad warps refuse or skip."""
    import pytest

    rng = np.random.default_rng(2)
    counts = rng.random((3, 20, 30)).astype(np.float32)
    acc = WarpAccumulator(20, 30)
    acc.add_many(counts[:1], np.array([4]), 2.0 * np.eye(3)[None])  # the identity, unnormalised
    np.testing.assert_array_equal(acc.counts, counts[0])
    np.testing.assert_array_equal(acc.frames, 4)
    # a perspective warp (corners moved by ~0.5 px by the perspective terms) against OpenCV's own
    tilt = geometry.translation(3, 2) @ np.array([[1, 0, 0], [0, 1, 0], [1e-4, 2e-4, 1.0]])
    acc = WarpAccumulator(40, 50)
    acc.add(counts[1], 1, tilt)
    import cv2

    expected = cv2.warpPerspective(counts[1], tilt, (50, 40), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    cover = cv2.warpPerspective(np.ones((20, 30), np.float32), tilt, (50, 40), flags=cv2.INTER_NEAREST)
    np.testing.assert_allclose(acc.counts, expected * cover, atol=1e-5)
    np.testing.assert_array_equal(acc.frames, cover)
    nowhere = np.full((3, 3), np.nan)
    acc.add(counts[2], 1, nowhere)  # NaN: no footprint, nothing added
    np.testing.assert_array_equal(acc.frames, cover)
    with pytest.raises(ValueError, match="degenerate"):
        acc.add(counts[2], 1, np.zeros((3, 3)))
