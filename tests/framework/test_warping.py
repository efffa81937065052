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
