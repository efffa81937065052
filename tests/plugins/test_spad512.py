"""Pi Imaging SPAD512 1-bit readouts: ``spad512``.

Readout files are written here with ``np.packbits`` in the documented layout (row-major
frames, 8 pixels per byte, most significant bit first; ``photoncube``'s SPAD512 reader
copies the bytes unchanged into its MSB-first cube), read back and compared bit for bit.
"""

import time
import warnings

import numpy as np
import pytest
from photonpano.errors import SourceError
from photonpano.host import PluginHost
from photonpano.plugins.sources.spad512 import SPAD512_FILE_BYTES, Spad512Config, Spad512Warning, write_spad512_files


def _frames(t, h, w, p=0.3, seed=0):
    """(t, h, w) uint8 Bernoulli(p) frames, drawn 64 frames at a time (one float64 draw of 1003 frames took 2.1 GB)."""
    rng, out = np.random.default_rng(seed), np.empty((t, h, w), np.uint8)
    for start in range(0, t, 64):
        out[start:start + 64] = rng.random((len(out[start:start + 64]), h, w), dtype=np.float32) < p
    return out


def _sums(frames, edges):
    return np.stack([frames[a:b].sum(0) for a, b in zip(edges[:-1], edges[1:])])


def test_default_files_are_1000_frames_of_512x512_msb_first(tmp_path):
    frames = _frames(1003, 512, 512, p=0.2, seed=1)
    files = write_spad512_files(frames, tmp_path / "cap")
    assert [f.stat().st_size for f in files] == [SPAD512_FILE_BYTES, 3 * 32768]
    # the layout by hand: frame 7, row 3, pixels 8..15 are byte 7 * 32768 + 3 * 64 + 1, MSB = pixel 8
    raw = files[0].read_bytes()
    byte = raw[7 * 32768 + 3 * 64 + 1]
    assert [(byte >> (7 - k)) & 1 for k in range(8)] == frames[7, 3, 8:16].tolist()
    with pytest.warns(Spad512Warning, match=r"spad512_00001\.bin is truncated \(98304 of 32768000 bytes\): using "
                                            r"its 3 whole frames"):
        src = Spad512Config(path=tmp_path / "cap").build()
    assert (src.n_frames, src.height, src.width, src.frames_per_file) == (1003, 512, 512, 1000)
    np.testing.assert_array_equal(np.unpackbits(src.read_frames(995, 1003), axis=-1), frames[995:1003])
    edges = np.array([0, 1, 500, 999, 1001, 1003])
    np.testing.assert_array_equal(src.sum_ranges(edges), _sums(frames, edges))
    assert src.describe()["notes"] == src.notes and src.describe()["frames_per_file"] == 1000
    assert PluginHost().hook.photonpano_source_for_input(path=tmp_path / "cap") == {
        "plugin": "spad512", "path": str(tmp_path / "cap")}


def test_settings_override_frame_size_bit_order_trailer_and_frame_range(tmp_path):
    frames = _frames(70, 24, 40, seed=2)
    files = write_spad512_files(frames, tmp_path / "lsb", 32, trailer=b"\x01\x02\x03\x04", bit_order="lsb")
    assert [f.stat().st_size for f in files] == [32 * 120 + 4, 32 * 120 + 4, 6 * 120]
    # LSB first: pixel 0 of frame 0 is bit 0 of byte 0
    assert files[0].read_bytes()[0] & 1 == frames[0, 0, 0]
    with pytest.warns(Spad512Warning, match="truncated"):
        src = Spad512Config(path=files, height=24, width=40, bit_order="lsb", trailer_bytes=4,
                            start=5, stop=66).build()
    assert (src.n_frames, src.frames_per_file, src.file_bytes) == (61, 32, 32 * 120 + 4)
    edges = np.array([0, 27, 28, 61])  # crosses both file boundaries and their trailers
    np.testing.assert_array_equal(src.sum_ranges(edges), _sums(frames[5:66], edges))
    np.testing.assert_array_equal(np.unpackbits(src.read_frames(20, 40), axis=-1), frames[25:45])
    # the wrong bit order mirrors every byte's 8 pixels: caught by comparing
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Spad512Warning)
        msb = Spad512Config(path=files, height=24, width=40, trailer_bytes=4).build()
    assert not np.array_equal(msb.sum_ranges(np.array([0, 70])), _sums(frames, np.array([0, 70])))
    # a hot pixel mask is inpainted, transforms rotate
    mask = np.zeros((24, 40), bool)
    mask[3, 7] = True
    np.save(tmp_path / "hot.npy", mask)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Spad512Warning)
        fixed = Spad512Config(path=files, height=24, width=40, bit_order="lsb", trailer_bytes=4,
                              inpaint_mask=tmp_path / "hot.npy", transforms=["rot90"]).build()
    assert (fixed.height, fixed.width) == (40, 24)
    counts = fixed.sum_ranges(np.array([0, 70]))[0]
    truth = np.rot90(frames.sum(0), -1)
    keep = np.rot90(~mask, -1)
    np.testing.assert_array_equal(counts[keep], truth[keep])


def test_bad_readouts_are_one_line_errors_naming_the_file_and_the_size(tmp_path):
    frames = _frames(40, 16, 16, seed=3)
    files = write_spad512_files(frames, tmp_path / "cap", 16)
    cut = tmp_path / "cut.bin"
    cut.write_bytes(files[0].read_bytes()[:500])  # 15 frames of 32 bytes and 20 stray bytes
    with pytest.raises(SourceError, match=r"^source \(spad512\): .*cut\.bin is 500 bytes, not a whole number of "
                                          r"16x16 1-bit frames \(32 bytes each\); expected a SPAD512 readout file "
                                          r"of 32768000 bytes \(1000 frames of 512x512\)") as err:
        Spad512Config(path=[cut, files[1]], height=16, width=16).build()
    assert "\n" not in str(err.value)
    with pytest.raises(SourceError, match=r"cut\.bin is 500 bytes; expected a SPAD512 readout file of 512 bytes "
                                          r"\(16 frames of 16x16\); only the last file may be truncated"):
        Spad512Config(path=[files[0], cut, files[1]], height=16, width=16).build()
    with pytest.warns(Spad512Warning, match=r"cut\.bin is truncated \(500 of 512 bytes\): using its 15 whole frames, "
                                            r"dropping 20 bytes"):
        src = Spad512Config(path=[cut], height=16, width=16, frames_per_file=16).build()
    assert src.n_frames == 15
    with pytest.raises(SourceError, match=r"no \.bin files in .*empty; expected SPAD512 readout files"):
        (tmp_path / "empty").mkdir()
        Spad512Config(path=tmp_path / "empty").build()
    with pytest.raises(SourceError, match=r"frames 0:99 are outside"), warnings.catch_warnings():
        warnings.simplefilter("ignore", Spad512Warning)
        Spad512Config(path=tmp_path / "cap", height=16, width=16, stop=99).build()
    with pytest.raises(ValueError, match="multiple of 8"):
        Spad512Config(path=tmp_path / "cap", width=20)


def test_pano_detection_tells_spad512_from_swissspad_files_by_size(tmp_path):
    host = PluginHost()
    gui = tmp_path / "gui"
    gui.mkdir()
    (gui / "acq_00000.bin").write_bytes(bytes(256 * 32768 + 4))  # SPAD512S GUI: 256 frames and 4 bytes
    assert host.hook.photonpano_source_for_input(path=gui) == {"plugin": "spad512", "path": str(gui),
                                                                "trailer_bytes": 4}
    src = Spad512Config(**{k: v for k, v in host.hook.photonpano_source_for_input(path=gui).items()
                           if k != "plugin"}).build()
    assert (src.n_frames, src.frames_per_file) == (256, 256)
    ss2 = tmp_path / "ss2"
    ss2.mkdir()
    (ss2 / "RAW00000.bin").write_bytes(bytes(8 * 2**20))  # SwissSPAD2: exactly 8 MiB
    assert host.hook.photonpano_source_for_input(path=ss2)["plugin"] == "swissspad-bin"


def test_simulated_capture_written_as_spad512_files_reconstructs_within_a_pixel(tmp_path):
    """End to end: ``simulate`` frames -> SPAD512 files -> ``spad512`` source -> pipeline -> RMSE vs truth."""
    from photonpano.metrics import trajectory_error
    from photonpano.pipeline import reconstruct
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.spec import apply_overrides, validate_spec

    cap = SimulateConfig(frames=2500, height=128, width=160, vibration_px=1.5).build()
    frames = np.unpackbits(np.asarray(cap.cube), axis=-1)
    write_spad512_files(frames, tmp_path / "cap")  # 1000 frames per file: two complete files and 500 frames
    data = apply_overrides({"source": {"plugin": "spad512", "path": str(tmp_path / "cap"), "height": 128,
                                       "width": 160}}, ["levels=2", "pair_offsets=[1,2,4]"])
    spec = validate_spec(data, PluginHost(), origin="test")
    with pytest.warns(Spad512Warning, match="truncated"):
        source = spec.source.build()
    np.testing.assert_array_equal(source.sum_ranges(np.array([0, 999, 2500])),
                                  cap.sum_ranges(np.array([0, 999, 2500])))
    t0 = time.perf_counter()
    homographies = reconstruct(spec, source)[0]
    assert homographies.shape == (2500, 3, 3)
    rmse = trajectory_error(homographies, cap.ground_truth, 160, 128).rmse_px
    assert rmse < 1.0, rmse
    assert time.perf_counter() - t0 < 120
