"""SwissSPAD2 readout layouts and sensor corrections, checked bit for bit.

The expected layouts are written here independently of :mod:`photonpano.plugins.sources._swissspad_readout`,
straight from the documented format (SOURCES.md): LSB first within a byte; full-array
records of 1024 pixels alternating quarter-rows of the top half and of the flipped
bottom half.
"""

import numpy as np
import pytest
from photonpano.errors import SourceError
from photonpano.photons import sum_packed_ranges
from photonpano.plugins.sources._swissspad_readout import (
    LAYOUTS,
    decode_frames,
    encode_frames,
    layout_scores,
    record_counts_to_frame,
)
from photonpano.plugins.sources._swissspad_sensor import (
    SensorCorrector,
    SwissSpadCorrections,
    bundled_sensor_file,
    load_cfa,
    load_mask,
    transform_matrix,
    transform_shape,
)


def documented_bytes(frames: np.ndarray, layout: str) -> np.ndarray:
    """(K, H, W) 0/1 frames -> (K, 8 MiB / frames_per_file) bytes in the documented layout."""
    k = len(frames)
    if layout == "full":
        records = np.empty((k, 256, 1024), np.uint8)
        for r in range(256):
            parts = []
            for q in range(4):
                parts += [frames[:, r, 128 * q:128 * (q + 1)], frames[:, 511 - r, 128 * q:128 * (q + 1)]]
            records[:, r] = np.concatenate(parts, axis=1)
        frames = records
    bits = frames.reshape(k, -1, 8)
    weights = 1 << np.arange(8)  # pixel 8j + k is bit k of byte j (LSB first)
    return (bits * weights).sum(-1).astype(np.uint8)


def corrector(**fields):
    return SensorCorrector(SwissSpadCorrections(plugin="test", **fields), (256, 512), "half", "test")


@pytest.fixture(scope="module")
def frames():
    return {name: (np.random.default_rng(3).random((6, lay.height, lay.width)) < 0.3).astype(np.uint8)
            for name, lay in LAYOUTS.items()}


@pytest.mark.parametrize("name", ["half", "full"])
def test_encode_and_decode_follow_the_documented_layout(frames, name):
    layout = LAYOUTS[name]
    f = frames[name]
    raw = encode_frames(np.packbits(f, axis=-1), layout)
    assert raw.shape == (6, layout.frame_bytes)
    assert layout.frame_bytes * layout.frames_per_file == 8 * 2**20
    np.testing.assert_array_equal(raw, documented_bytes(f, name))
    np.testing.assert_array_equal(np.unpackbits(decode_frames(raw, layout), axis=-1), f)


@pytest.mark.parametrize("name", ["half", "full"])
def test_counts_of_raw_records_land_on_the_right_pixels(frames, name):
    layout = LAYOUTS[name]
    f = frames[name]
    raw = documented_bytes(f, name).reshape((6,) + layout.record_shape)
    counts = record_counts_to_frame(sum_packed_ranges(raw, np.array([0, 1, 4, 6])), layout)
    want = np.stack([f[0:1].sum(0), f[1:4].sum(0), f[4:6].sum(0)])
    np.testing.assert_array_equal(counts, want)


def test_layout_scores_tell_half_from_full():
    # a smooth ramp scene: the wrong layout puts distant quarter-rows side by side
    y, x = np.mgrid[0:512, 0:512]
    p = 0.1 + 0.8 * (x / 511) * (0.2 + 0.8 * y / 511)
    full = (np.random.default_rng(0).random((256, 512, 512)) < p).astype(np.uint8)  # one file
    raw_full = encode_frames(np.packbits(full, axis=-1), LAYOUTS["full"])
    scores = layout_scores(raw_full)
    assert scores["full"] < 1.5 and scores["half"] > 4 * scores["full"]
    half = (np.random.default_rng(1).random((512, 256, 512)) < p[:256]).astype(np.uint8)
    raw_half = encode_frames(np.packbits(half, axis=-1), LAYOUTS["half"])
    scores = layout_scores(raw_half)
    assert scores["half"] < 1.5 and scores["full"] > 4 * scores["half"]


def test_colorspad_fix_crops_and_swaps_columns_exactly():
    raw = np.arange(2 * 256 * 512, dtype=np.uint16).reshape(2, 256, 512) % 65535
    out = corrector(fix="colorspad").apply(raw.copy(), np.array([0, 1, 2]))
    assert out.shape == (2, 254, 496)
    want = raw[:, 2:, :496].copy()
    want[:, :, 252:256], want[:, :, 260:264] = raw[:, 2:, 260:264], raw[:, 2:, 252:256]
    np.testing.assert_array_equal(out, want)


def test_grayspad_fix_half_and_full():
    raw = np.random.default_rng(1).integers(0, 50, (1, 256, 512)).astype(np.uint16)
    np.testing.assert_array_equal(corrector(fix="grayspad").apply(raw.copy(), np.array([0, 50])), raw[:, 2:, :496])
    full = np.random.default_rng(2).integers(0, 50, (1, 512, 512)).astype(np.uint16)
    c = SensorCorrector(SwissSpadCorrections(plugin="t", fix="grayspad"), (512, 512), "full", "t")
    assert c.corrected_shape == (509, 496)
    out = c.geometry(full)
    np.testing.assert_array_equal(out[0, :252], full[0, 2:254, :496])
    np.testing.assert_array_equal(out[0, 255:], full[0, 256:510, :496])
    np.testing.assert_array_equal(out[0, 252:254], full[0, 254:256, :496])
    assert c.missing[254].all() and c.missing.sum() == 496  # the blank row between halves is inpainted


@pytest.mark.parametrize("transforms", [["rot90"], ["rot270"], ["rot180"], ["flip-ud"], ["flip-lr"],
                                        ["rot90", "flip-ud"]])
def test_transforms_match_their_pixel_maps(transforms):
    rng = np.random.default_rng(4)
    raw = rng.integers(0, 100, (1, 256, 512)).astype(np.uint16)
    c = corrector(fix="colorspad", transforms=transforms)
    out = c.apply(raw.copy(), np.array([0, 100]))[0]
    base = corrector(fix="colorspad").apply(raw.copy(), np.array([0, 100]))[0]
    assert out.shape == transform_shape((254, 496), transforms) == c.shape
    m = transform_matrix((254, 496), transforms)
    ys, xs = rng.integers(0, 254, 50), rng.integers(0, 496, 50)
    xt, yt, _ = m @ np.stack([xs, ys, np.ones(50)])
    np.testing.assert_array_equal(out[np.rint(yt).astype(int), np.rint(xt).astype(int)], base[ys, xs])
    if transforms == ["rot90"]:  # clockwise as displayed: the top-left corner goes to the top right
        assert out[0, -1] == base[0, 0]


def test_inpainting_is_unbiased_integer_and_repeatable(tmp_path):
    mask = np.zeros((20, 30), bool)
    mask[10, 10] = mask[5, 0] = True
    mask[3:6, 20:23] = True  # the centre pixel (4, 21) has no valid 4-neighbour
    path = tmp_path / "mask.npy"
    np.save(path, mask)
    c = SensorCorrector(SwissSpadCorrections(plugin="t", inpaint_mask=path), (20, 30), None, "t")
    assert c.active and (c.missing == mask).all()
    assert not SensorCorrector(SwissSpadCorrections(plugin="t"), (20, 30), None, "t").active
    counts = np.full((4000, 20, 30), 4, np.uint16)
    counts[:, 9, 10] = 3  # neighbours of (10, 10): 3, 4, 4, 4 -> mean 3.75
    counts[:, mask] = 60000  # whatever a hot pixel counted is replaced
    edges = np.arange(0, 4001) * 10
    out = c.apply(counts.copy(), edges)
    assert out.dtype == np.uint16 and out.shape == (4000, 20, 30)
    assert set(np.unique(out[:, 10, 10])) == {3, 4}
    assert abs(out[:, 10, 10].mean() - 3.75) < 0.03  # stochastic rounding keeps the expectation
    assert (out[:, 4, 21] == 4).all() and (out[:, 5, 0] == 4).all()
    np.testing.assert_array_equal(out[:, ~mask], counts[:, ~mask])
    np.testing.assert_array_equal(out, c.apply(counts.copy(), edges))  # same ranges, same counts


def test_bundled_mask_and_cfa_load_with_the_documented_meaning():
    mask = load_mask(bundled_sensor_file("inpaint_mask"), (254, 496))
    assert mask.dtype == bool and 0.03 < mask.mean() < 0.05
    cfa = load_cfa(bundled_sensor_file("cfa"), (254, 496))
    codes, counts = np.unique(cfa, return_counts=True)
    assert codes.tolist() == [-1, 0, 1, 2]
    assert (cfa[::2] == -1).all() and (cfa[:, ::2] == -1).all()  # filters on odd rows and columns only
    assert abs(counts[1] - counts[2]) < 50 and abs(counts[1] - counts[3]) < 50
    c = corrector(fix="colorspad", cfa="colorspad", inpaint_mask="colorspad", transforms=["rot90"])
    assert c.cfa.shape == c.shape == (496, 254)
    assert c.missing.sum() == (np.rot90(cfa, -1) >= 0).sum() + (np.rot90(mask & (cfa < 0), -1)).sum()


def test_bad_corrections_are_one_line_errors(tmp_path):
    with pytest.raises(SourceError, match=r"fix colorspad expects raw SwissSPAD2 half-array frames of 256x512, got "
                                          r"254x496"):
        SensorCorrector(SwissSpadCorrections(plugin="t", fix="colorspad"), (254, 496), None, "cube.npy")
    small = tmp_path / "small.npy"
    np.save(small, np.zeros((10, 10), bool))
    with pytest.raises(SourceError, match=r"small\.npy has shape \(10, 10\); expected at least \(254, 496\)"):
        corrector(fix="colorspad", inpaint_mask=small)
    import cv2

    odd = tmp_path / "odd.png"
    cv2.imwrite(str(odd), np.full((256, 512, 3), 128, np.uint8))
    with pytest.raises(SourceError, match=r"odd\.png has pixel \(0, 0\) of colour \[128, 128, 128\]"):
        corrector(fix="colorspad", cfa=odd)
    with pytest.raises(ValueError, match="colour_panorama needs cfa"):
        SwissSpadCorrections(plugin="t", colour_panorama=True)
    assert "\n" not in str(SourceError("x"))
