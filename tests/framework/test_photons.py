import numpy as np
import pytest
from photonpano import photons


def test_sum_packed_ranges_matches_unpacked_sum():
    rng = np.random.default_rng(1)
    frames = (rng.random((700, 5, 24)) < 0.4).astype(np.uint8)
    packed = np.packbits(frames, axis=-1)
    edges = np.array([3, 4, 300, 700])  # includes ranges longer than 255 frames
    got = photons.sum_packed_ranges(packed, edges)
    want = np.stack([frames[a:b].sum(0) for a, b in zip(edges[:-1], edges[1:])])
    assert got.dtype == np.uint16 and got.shape == (3, 5, 24)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(photons.sum_unpacked_ranges(frames, edges), want)


def test_sum_packed_ranges_counts_every_byte_value():
    """Each of the 256 byte values, in every byte position, spreads into its 8 pixels (MSB first)."""
    values = (np.arange(600)[:, None, None] * 7 + np.arange(3)[None, :, None] * 31 + np.arange(4)) % 256
    packed = values.astype(np.uint8)  # (600, 3, 4): every value in every position, 600 > 2 x 255 frames
    edges = np.array([0, 1, 256, 600])
    want = np.stack([np.unpackbits(packed[a:b], axis=-1).sum(0) for a, b in zip(edges[:-1], edges[1:])])
    np.testing.assert_array_equal(photons.sum_packed_ranges(packed, edges), want)


@pytest.mark.parametrize("edges", [[5, 5], [0, 701], [-1, 3]])
def test_sum_ranges_rejects_bad_edges(edges):
    with pytest.raises(ValueError):
        photons.sum_packed_ranges(np.zeros((700, 2, 1), np.uint8), np.array(edges))


def test_simulated_frames_follow_bernoulli_and_are_reproducible():
    p = np.full((64, 64), 0.3, dtype=np.float32)
    p[:, :32] = 0.05
    a = np.stack([np.unpackbits(photons.simulate_packed_frames(p, 7, t), axis=-1) for t in range(400)])
    b = photons.simulate_packed_frames(p, 7, 11)
    np.testing.assert_array_equal(np.unpackbits(b, axis=-1), a[11])
    # mean detection rate within 4 standard errors of the probability
    for cols, prob in ((slice(0, 32), 0.05), (slice(32, 64), 0.3)):
        rate = a[:, :, cols].mean()
        assert abs(rate - prob) < 4 * np.sqrt(prob * (1 - prob) / a[:, :, cols].size)
    assert not np.array_equal(a[0], a[1])


def test_simulate_rejects_unpackable_width():
    with pytest.raises(ValueError, match="multiple of 8"):
        photons.simulate_packed_frames(np.zeros((4, 12), np.float32), 0, 0)


def test_flux_mle_recovers_flux():
    # Eq. (3): phi = -ln(1 - S/n) / tau
    rng = np.random.default_rng(2)
    tau, phi = 1e-5, np.array([[2e3, 5e4, 2e5]])
    n = 20_000
    counts = rng.binomial(n, 1 - np.exp(-phi * tau))
    est = photons.flux_mle(counts, n, tau)
    np.testing.assert_allclose(est, phi, rtol=0.03)
    assert est.dtype == np.float32


def test_flux_mle_marks_unobserved_and_saturated():
    est = photons.flux_mle(np.array([[0.0, 10.0]]), np.array([[0.0, 10.0]]), 1e-5)
    assert np.isnan(est[0, 0]) and np.isfinite(est[0, 1])


def test_srgb_roundtrip_and_tone_map():
    x = np.linspace(0, 1, 11, dtype=np.float32)
    np.testing.assert_allclose(photons.srgb_to_linear(photons.linear_to_srgb(x)), x, atol=1e-6)
    img = photons.tone_map(np.array([[np.nan, 0.0, 1.0, 2.0]]), percentile=100, bits=16)
    assert img.dtype == np.uint16 and img[0, 0] == 0 and img[0, 3] == 65535
    with pytest.raises(ValueError):
        photons.tone_map(np.zeros((2, 2)), bits=12)


def test_tone_map_table_is_within_one_level_of_the_srgb_curve():
    from photonpano.photons import linear_to_srgb, tone_map

    flux = np.random.default_rng(3).gamma(2.0, 500.0, (64, 80)).astype(np.float32)
    flux[:3] = np.nan
    white = np.sort(flux[np.isfinite(flux)])[int(round((np.isfinite(flux).sum() - 1) * 0.995))]
    exact = np.rint(linear_to_srgb(np.nan_to_num(flux) / white) * 255)
    image = tone_map(flux)
    assert image.dtype == np.uint8 and np.abs(image - exact).max() <= 1
    assert (image[:3] == 0).all() and image.max() == 255


def test_tone_map_kernel_equals_the_numpy_formula():
    """The compiled 8-bit path is the table lookup of clip(flux * (top / white) + 0.5) in float32, NaN -> 0."""
    from photonpano.photons import _srgb_table, tone_map

    def reference(f, percentile=99.5):
        values = f[np.isfinite(f)]
        white = float(np.partition(values, int(round((values.size - 1) * percentile / 100)))[
            int(round((values.size - 1) * percentile / 100))]) if values.size else 1.0
        white = white if white > 0 else 1.0
        table = _srgb_table()
        index = f * np.float32((len(table) - 1) / white) + np.float32(0.5)
        return table[np.nan_to_num(np.clip(index, 0, len(table) - 1), nan=0.0).astype(np.int32)]

    rng = np.random.default_rng(8)
    for trial in range(12):
        f = rng.gamma(2.0, 1000.0, tuple(rng.integers(1, 90, 2))).astype(np.float32)
        f[rng.random(f.shape) < 0.1] = np.nan
        f[rng.random(f.shape) < 0.02] = (np.inf, -np.inf, -3.0)[trial % 3]
        for flux in (f, f.T, np.full_like(f, np.nan), np.zeros_like(f)):  # strided, unobserved, black
            np.testing.assert_array_equal(tone_map(flux), reference(np.asarray(flux)))
    np.testing.assert_array_equal(tone_map(f.astype(np.float64), percentile=50), reference(f, 50))


def test_counting_kernels_add_into_the_callers_rows():
    """`out=` accumulates (the streaming loop's chunks add into the same ranges) and is checked."""
    from photonpano.photons import sum_packed_ranges, sum_unpacked_ranges

    rng = np.random.default_rng(3)
    frames = (rng.random((40, 6, 16)) < 0.3).astype(np.uint8)
    cube = np.packbits(frames, axis=-1)
    edges = np.array([0, 10, 40])
    expected = np.stack([frames[0:10].sum(0), frames[10:40].sum(0)]).astype(np.uint16)
    for count, data in ((sum_packed_ranges, cube), (sum_unpacked_ranges, frames)):
        out = np.full((2, 6, 16), 5, np.uint16)
        assert count(data, edges, out=out) is out
        np.testing.assert_array_equal(out, expected + 5)
    with pytest.raises(ValueError, match="C-contiguous uint16"):
        sum_packed_ranges(cube, edges, out=np.zeros((2, 6, 16), np.int32))


@pytest.mark.parametrize("start, stop", [(-1, 5), (6, 5), (0, 101)])
def test_check_frame_range_refuses_ranges_outside_the_capture(start, stop):
    from photonpano.photons import check_frame_range

    check_frame_range(0, 100, 100)
    check_frame_range(100, 100, 100)  # an empty range at the end is inside
    with pytest.raises(ValueError, match=f"frames {start}:{stop} leave the capture of 100 frames"):
        check_frame_range(start, stop, 100)
