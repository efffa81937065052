"""SwissSPAD2 raw readouts: ``swissspad-bin``, ``convert``, corrections on ``npy-cube``.

Readout files are written in the documented layouts (``tests/plugins/test_swissspad_sensor.py``
checks those writers against an independent implementation), read back and compared
bit for bit; the optional cross-check reads the same files with the sensor authors'
``photoncube`` package.
"""

import hashlib
import json
import warnings

import numpy as np
import pytest
from capture_helpers import simulate_raw_half
from photonpano.cli import app
from photonpano.errors import SourceError
from photonpano.plugins.sources._swissspad_readout import LAYOUTS, write_bin_files
from photonpano.plugins.sources.npy_cube import NpyCubeConfig
from photonpano.plugins.sources.swissspad import SourceWarning, SwissSpadBinConfig
from typer.testing import CliRunner

runner = CliRunner()


@pytest.fixture(scope="module")
def raw_capture(tmp_path_factory):
    """1 300 frames of a simulated colour half array at the raw layout, in three files.

    The last file is truncated mid-frame (276 whole frames and 1 000 stray bytes).
    """
    cap, raw = simulate_raw_half(1300, flux=0.3, speed_px_per_frame=0.05, vibration_px=1.0)
    folder = tmp_path_factory.mktemp("bin") / "capture"
    files = write_bin_files(raw, folder)
    with open(files[-1], "ab") as f:
        f.write(b"\x55" * 1000)
    return cap, raw, folder, files


def _digests(paths):
    return [hashlib.sha256(p.read_bytes()).hexdigest() for p in paths]


def test_half_array_files_read_back_bit_exact_with_a_truncated_last_file(raw_capture):
    cap, raw, folder, files = raw_capture
    before = _digests(files)
    with pytest.warns(SourceWarning, match=r"RAW00002\.bin is truncated \(4522984 of 8388608 bytes\): using its "
                                           r"276 whole frames, dropping 1000 bytes"):
        src = SwissSpadBinConfig(path=folder).build()
    assert (src.n_frames, src.height, src.width) == (1300, 256, 512)
    assert src.describe()["notes"] == src.notes and len(src.notes) == 1
    np.testing.assert_array_equal(src.read_frames(500, 530), raw[500:530])  # crosses the first file boundary
    edges = np.array([0, 7, 511, 513, 1024, 1300])
    frames = np.unpackbits(raw, axis=-1)
    want = np.stack([frames[a:b].sum(0) for a, b in zip(edges[:-1], edges[1:])])
    np.testing.assert_array_equal(src.sum_ranges(edges), want)
    assert _digests(files) == before  # inputs are never written


def test_full_array_files_read_back_bit_exact(tmp_path):
    frames = (np.random.default_rng(5).random((300, 512, 512), dtype=np.float32) < 0.25).astype(np.uint8)
    files = write_bin_files(np.packbits(frames, axis=-1), tmp_path / "full", "full")
    assert [f.stat().st_size for f in files] == [8 * 2**20, 44 * 32768]
    with pytest.warns(SourceWarning):
        src = SwissSpadBinConfig(path=files, layout="full", check_layout=False).build()
    assert (src.n_frames, src.height, src.width) == (300, 512, 512)
    np.testing.assert_array_equal(np.unpackbits(src.read_frames(250, 300), axis=-1), frames[250:300])
    np.testing.assert_array_equal(src.sum_ranges(np.array([3, 255, 257, 300])),
                                  np.stack([frames[3:255].sum(0), frames[255:257].sum(0), frames[257:].sum(0)]))
    src = SwissSpadBinConfig(path=files[0], layout="full", fix="grayspad", start=10, stop=20,
                             check_layout=False).build()
    assert (src.n_frames, src.height, src.width) == (10, 509, 496)
    counts = src.sum_ranges(np.array([0, 10]))[0]
    np.testing.assert_array_equal(counts[:252], frames[10:20, 2:254, :496].sum(0))
    np.testing.assert_array_equal(counts[255:], frames[10:20, 256:510, :496].sum(0))


def test_colorspad_fix_on_bin_files_and_on_the_converted_cube_agree(raw_capture, tmp_path):
    cap, raw, folder, files = raw_capture
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SourceWarning)
        src = SwissSpadBinConfig(path=folder, fix="colorspad").build()
    assert (src.height, src.width) == (254, 496)
    edges = np.array([0, 300, 700, 1300])
    truth = cap.sum_ranges(edges)  # the simulated sensor frames, before the embedding
    np.testing.assert_array_equal(src.sum_ranges(edges), truth)
    out = tmp_path / "cube.npy"
    result = runner.invoke(app, ["convert", str(folder), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output and "1300 half-array frames" in result.output
    cube = np.load(out, mmap_mode="r")
    assert cube.shape == (1300, 256, 64) and cube.dtype == np.uint8
    np.testing.assert_array_equal(cube, raw)
    npy = NpyCubeConfig(path=out, fix="colorspad", inpaint_mask="colorspad", transforms=["rot90", "flip-ud"]).build()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SourceWarning)
        binary = SwissSpadBinConfig(path=folder, fix="colorspad", inpaint_mask="colorspad",
                                    transforms=["rot90", "flip-ud"]).build()
    assert (npy.height, npy.width) == (binary.height, binary.width) == (496, 254)
    edges = np.array([0, 13, 600, 1299])
    np.testing.assert_array_equal(npy.sum_ranges(edges), binary.sum_ranges(edges))
    again = runner.invoke(app, ["convert", str(folder), "-o", str(out)])
    assert again.exit_code == 1 and "exists; refusing to overwrite" in again.output


def test_bad_readouts_are_one_line_errors_naming_the_file(raw_capture, tmp_path):
    cap, raw, folder, files = raw_capture
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match=r"no \.bin files in .*empty; expected SwissSPAD2 raw readout files"):
        SwissSpadBinConfig(path=tmp_path / "empty").build()
    short = tmp_path / "short.bin"
    short.write_bytes(files[0].read_bytes()[:5000])
    with pytest.raises(SourceError, match=r"short\.bin is 5000 bytes; expected a SwissSPAD2 raw readout file of "
                                          r"8388608 bytes .*only the last file may be truncated"):
        SwissSpadBinConfig(path=[short, files[1]]).build()
    short.write_bytes(b"x" * 100)
    with pytest.raises(SourceError, match=r"short\.bin holds no whole half-array frame"), warnings.catch_warnings():
        warnings.simplefilter("ignore", SourceWarning)
        SwissSpadBinConfig(path=[short]).build()
    with pytest.raises(SourceError, match=r"RAW00000\.bin does not look like full-array readouts .* expected "
                                          r"layout: half"), warnings.catch_warnings():
        warnings.simplefilter("ignore", SourceWarning)
        SwissSpadBinConfig(path=folder, layout="full").build()
    with pytest.raises(SourceError, match="frames 0:5000 are outside capture, which holds 1300 whole frames"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SourceWarning)
            SwissSpadBinConfig(path=folder, stop=5000).build()


def test_pano_picks_the_bin_source_for_a_folder(host, raw_capture, tmp_path):
    cap, raw, folder, files = raw_capture
    assert host.hook.photonpano_source_for_input(path=folder) == {"plugin": "swissspad-bin", "path": str(folder)}
    assert host.hook.photonpano_source_for_input(path=files[0])["plugin"] == "swissspad-bin"
    result = runner.invoke(app, ["convert", str(tmp_path / "nothing"), "-o", str(tmp_path / "x.npy")])
    assert result.exit_code == 1 and "does not exist" in result.output


def test_photoncube_reads_the_same_files_identically(tmp_path):
    photoncube = pytest.importorskip("photoncube")
    rng = np.random.default_rng(9)
    for name in ("half", "full"):
        layout = LAYOUTS[name]
        frames = (rng.random((layout.frames_per_file * 2, layout.height, layout.width), dtype=np.float32)
                  < 0.3).astype(np.uint8)
        folder = tmp_path / name
        write_bin_files(np.packbits(frames, axis=-1), folder, layout)
        theirs = tmp_path / f"{name}.npy"
        photoncube.PhotonCube.convert_to_npy(str(folder), str(theirs), is_full_array=name == "full")
        src = SwissSpadBinConfig(path=folder, layout=name, check_layout=False).build()
        np.testing.assert_array_equal(np.load(theirs), src.read_frames(0, src.n_frames))
    # the colour-SPAD fix and the paper's rotate-and-flip, frame by frame
    cube = photoncube.PhotonCube.open(str(tmp_path / "half.npy"))
    cube.set_transforms([photoncube.Transform.Rot90, photoncube.Transform.FlipUD])
    processed = tmp_path / "processed.npy"
    cube.process_cube(str(processed), colorspad_fix=True)
    theirs = np.unpackbits(np.load(processed)[:20], axis=-1)
    ours = SwissSpadBinConfig(path=tmp_path / "half", fix="colorspad", transforms=["rot90", "flip-ud"],
                              check_layout=False).build().sum_ranges(np.arange(21))
    assert ours.shape == (20, 496, 254)
    np.testing.assert_array_equal(theirs[:, :, :254], ours)


@pytest.mark.slow
def test_raw_readouts_reconstruct_accurately_and_convert_gives_identical_homographies(tmp_path):
    """Acceptance: ``pano FOLDER --set source.fix=colorspad`` within 1 px; ``convert`` then ``.npy``: same result."""
    from photonpano.metrics import trajectory_error

    cap, raw = simulate_raw_half(4300, vibration_px=2.0)
    folder = tmp_path / "capture"
    write_bin_files(raw, folder)  # 8 full files and a truncated ninth (204 frames)
    settings = ["--set", "levels=2", "--set", "pair_offsets=[1,2,4]"]
    with pytest.warns(SourceWarning, match=r"RAW00008\.bin is truncated .* using its 204 whole frames"):
        result = runner.invoke(app, ["pano", str(folder), "-o", str(tmp_path / "bin"), "--set", "source.fix=colorspad",
                                     *settings])
    assert result.exit_code == 0, result.output
    h_bin = np.load(tmp_path / "bin" / "homographies.npy")
    assert h_bin.shape == (4300, 3, 3)
    rmse = trajectory_error(h_bin, cap.ground_truth, 496, 254).rmse_px
    assert rmse <= 1.0
    run = json.loads((tmp_path / "bin" / "run.json").read_text())
    assert run["source"]["files"] == 9 and "truncated" in run["source"]["notes"][0]

    assert runner.invoke(app, ["convert", str(folder), "-o", str(tmp_path / "cube.npy")]).exit_code == 0
    result = runner.invoke(app, ["pano", str(tmp_path / "cube.npy"), "-o", str(tmp_path / "npy"),
                                 "--set", "source.fix=colorspad", *settings])
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(np.load(tmp_path / "npy" / "homographies.npy"), h_bin)
