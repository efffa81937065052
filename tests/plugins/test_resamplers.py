import numpy as np
import pytest
from photonpano.plugins.resamplers.midpoint import ConstantConfig, MidpointConfig


def test_midpoint_level_one_is_n_over_m_centred_groups():
    g = MidpointConfig().build().groups(10_000, 500, 1)
    assert len(g) == 20
    np.testing.assert_array_equal(g.reference, np.arange(20) * 500 + 250)
    np.testing.assert_array_equal(g.stop - g.start, 500)
    np.testing.assert_array_equal(g.reference - g.start, 250)


@pytest.mark.parametrize("n_frames, group_size", [(20_000, 838), (10_250, 500), (10_240, 500), (5, 2), (101, 2)])
def test_midpoint_level_one_spreads_its_groups_over_the_whole_capture(n_frames, group_size):
    # floor(n / m) groups end to end left up to m - 1 frames after the last one, where the
    # trajectory was extrapolated (a half-lit capture with m = 838 whole lamp periods: 726 frames)
    g = MidpointConfig().build().groups(n_frames, group_size, 1)
    assert len(g) == max(2, round(n_frames / group_size + 1e-9))
    assert (g.start[0], g.stop[-1]) == (0, n_frames)
    np.testing.assert_array_equal(g.stop - g.start, group_size)
    spacing = np.diff(g.reference)
    assert np.all(spacing > 0) and spacing.max() - spacing.min() <= 1


def test_midpoint_adds_groups_between_previous_ones():
    resampler = MidpointConfig(anchor_ends=False).build()
    levels = [resampler.groups(10_000, 500, k).reference for k in (1, 2, 3)]
    assert [len(r) for r in levels] == [20, 39, 77]
    for coarse, fine in zip(levels, levels[1:]):
        assert set(coarse) <= set(fine)  # earlier centres are kept
        np.testing.assert_array_equal(fine[1::2], (coarse[:-1] + coarse[1:]) // 2)


def test_midpoint_anchors_the_ends_from_level_two():
    g = MidpointConfig().build().groups(10_000, 500, 2)
    assert g.reference[0] == 0 and g.reference[-1] == 9_999
    assert (g.start[0], g.stop[0]) == (0, 250) and (g.start[-1], g.stop[-1]) == (9_750, 10_000)
    assert MidpointConfig().build().groups(10_000, 500, 1).reference[0] == 250


def test_constant_keeps_the_level_one_groups():
    r = ConstantConfig().build()
    np.testing.assert_array_equal(r.groups(5_000, 500, 3).reference, r.groups(5_000, 500, 1).reference)


def test_too_short_capture_is_a_clear_error():
    with pytest.raises(ValueError, match="at least 2"):
        MidpointConfig().build().groups(700, 500, 1)


@pytest.mark.parametrize("n_frames, group_size", [(4, 2), (100, 2), (101, 2), (9, 3)])
def test_midpoint_end_anchors_never_repeat_a_reference(n_frames, group_size):
    # groups of 1-2 frames put a reference on an end frame already: anchoring it again
    # made the references not strictly increasing (the 4-frame beam clip failed so)
    g = MidpointConfig().build().groups(n_frames, group_size, 2)
    assert g.reference.dtype == np.int64 and np.all(np.diff(g.reference) > 0)
    assert (g.reference[0], g.reference[-1]) == (0, n_frames - 1)
    assert np.all(g.start <= g.reference) and np.all(g.reference < g.stop) and g.stop[-1] == n_frames


def test_midpoint_refuses_levels_closer_than_a_frame():
    resampler = MidpointConfig().build()
    assert len(resampler.groups(10_000, 16, 5)) > 0  # 16 / 2**4 = 1 frame apart: the last level with room
    with pytest.raises(ValueError, match=r"groups of 16 frames allow at most 5 levels: level 6's would be centred "
                                         r"0\.5 frames apart"):
        resampler.groups(10_000, 16, 6)
    with pytest.raises(ValueError, match="groups of 2 frames allow at most 2 levels"):
        resampler.groups(4, 2, 3)


@pytest.mark.parametrize("n_frames", [1, 2, 3])
def test_a_capture_under_four_frames_is_too_short_for_anything(n_frames):
    with pytest.raises(ValueError, match=f"a capture of {n_frames} frames? is too short to register: at least 4"):
        MidpointConfig().build().groups(n_frames, 2, 1)
