"""The ``zarr-cube`` source, ``convert`` between .npy and .zarr, and sources that pickle as "reopen this file".

Counts read through zarr must equal those read from the same cube as ``.npy`` bit for
bit (whatever the chunking and frame range), and a pickled file-backed source must
carry its settings, not its photons.
"""

import pickle
import warnings

import numpy as np
import pytest
from photonpano.cli import app
from photonpano.errors import SourceError
from photonpano.plugins.sources.npy_cube import NpyCubeConfig
from photonpano.testing import SourceContract, tiny_capture
from typer.testing import CliRunner

zarr = pytest.importorskip("zarr")

from photonpano.plugins.sources.zarr_cube import ZarrCubeConfig, convert_npy_to_zarr  # noqa: E402

runner = CliRunner()


class TestZarrCube(SourceContract):
    config_class = ZarrCubeConfig
    entry_point = "zarr-cube"

    def make_config(self, tmp_path_factory):
        folder = tmp_path_factory.mktemp("zarr")
        np.save(folder / "cube.npy", np.asarray(tiny_capture(frames=200).cube))
        convert_npy_to_zarr(folder / "cube.npy", folder / "cube.zarr")
        return ZarrCubeConfig(path=folder / "cube.zarr")


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    """2 500 bit-packed frames of 24x64 with random photons (p = 0.3), as .npy."""
    rng = np.random.default_rng(3)
    path = tmp_path_factory.mktemp("cube") / "cube.npy"
    np.save(path, np.packbits(rng.random((2500, 24, 64)) < 0.3, axis=-1))
    return path


def test_zarr_counts_equal_npy_counts_for_any_chunking_and_frame_range(cube, tmp_path):
    # chunks of 100 frames; 2 KiB read blocks = one chunk, so reads start mid-chunk and cross chunks
    convert_npy_to_zarr(cube, tmp_path / "c.zarr", chunk_bytes=100 * 24 * 8)
    assert zarr.open_array(str(tmp_path / "c.zarr"), mode="r").chunks == (100, 24, 8)
    edges = np.array([0, 1, 99, 100, 101, 777, 1500, 2210])
    for chunk_mb in (0.002, 1.0):
        npy = NpyCubeConfig(path=cube, start=37, stop=2250, chunk_mb=chunk_mb).build()
        zr = ZarrCubeConfig(path=tmp_path / "c.zarr", start=37, stop=2250, chunk_mb=chunk_mb).build()
        assert (zr.n_frames, zr.height, zr.width, zr.packed) == (2213, 24, 64, True)
        np.testing.assert_array_equal(zr.sum_ranges(edges), npy.sum_ranges(edges))
    frames = np.unpackbits(np.load(cube)[37:2250], axis=-1)
    np.testing.assert_array_equal(zr.sum_ranges(edges[:3])[1], frames[1:99].sum(0))


def test_unpacked_bool_cube_and_settings_carry_over(tmp_path):
    rng = np.random.default_rng(4)
    frames = rng.random((300, 16, 40)) < 0.2
    np.save(tmp_path / "u.npy", frames)
    convert_npy_to_zarr(tmp_path / "u.npy", tmp_path / "u.zarr")
    src = ZarrCubeConfig(path=tmp_path / "u.zarr", frame_rate_hz=50_000, exposure_s=1e-5).build()
    assert (src.packed, src.width, src.frame_rate_hz, src.exposure_s) == (False, 40, 50_000, 1e-5)
    np.testing.assert_array_equal(src.sum_ranges(np.array([0, 300]))[0], frames.sum(0))
    with pytest.raises(SourceError, match=r"source \(zarr-cube\): .*u\.zarr holds bool frames"):
        ZarrCubeConfig(path=tmp_path / "u.zarr", layout="packed").build()


def test_bad_zarr_inputs_are_one_line_errors_naming_the_path(tmp_path, cube):
    with pytest.raises(SourceError, match=r"source \(zarr-cube\): .*missing\.zarr does not exist"):
        ZarrCubeConfig(path=tmp_path / "missing.zarr").build()
    (tmp_path / "empty.zarr").mkdir()
    with pytest.raises(SourceError, match=r"source \(zarr-cube\): .*empty\.zarr is not a zarr array"):
        ZarrCubeConfig(path=tmp_path / "empty.zarr").build()
    flat = zarr.open_array(str(tmp_path / "flat.zarr"), mode="w", shape=(10, 10), dtype="u1")
    flat[:] = 1
    with pytest.raises(SourceError, match=r"flat\.zarr has shape \(10, 10\); expected a photon cube"):
        ZarrCubeConfig(path=tmp_path / "flat.zarr").build()
    convert_npy_to_zarr(cube, tmp_path / "c.zarr")
    with pytest.raises(SourceError, match=r"frames 0:9999 are outside .*c\.zarr, which holds 2500 frames"):
        ZarrCubeConfig(path=tmp_path / "c.zarr", stop=9999).build()


def test_convert_npy_to_zarr_and_back_is_exact_and_never_overwrites(cube, tmp_path, host):
    out = runner.invoke(app, ["convert", str(cube), "-o", str(tmp_path / "c.zarr")])
    assert out.exit_code == 0, out.output
    assert "wrote" in out.output and "2500 frames" in out.output
    out = runner.invoke(app, ["convert", str(tmp_path / "c.zarr"), "-o", str(tmp_path / "back.npy")])
    assert out.exit_code == 0, out.output
    np.testing.assert_array_equal(np.load(tmp_path / "back.npy"), np.load(cube))
    before = (tmp_path / "back.npy").read_bytes()
    out = runner.invoke(app, ["convert", str(tmp_path / "c.zarr"), "-o", str(tmp_path / "back.npy")])
    assert out.exit_code == 1 and "back.npy exists; refusing to overwrite it" in out.output
    assert (tmp_path / "back.npy").read_bytes() == before
    assert not list(tmp_path.glob("*.part"))
    out = runner.invoke(app, ["convert", str(cube), str(tmp_path / "back.npy"), "-o", str(tmp_path / "two.zarr")])
    assert out.exit_code == 1 and "a .zarr cube is written from one .npy cube" in out.output
    from photonpano.presets import spec_for_capture

    assert spec_for_capture(tmp_path / "c.zarr", host) == {"source": {"plugin": "zarr-cube",
                                                                      "path": str(tmp_path / "c.zarr")}}


def test_file_sources_pickle_as_their_settings_not_their_photons(tmp_path):
    rng = np.random.default_rng(5)
    np.save(tmp_path / "big.npy", np.packbits(rng.random((20_000, 64, 128), np.float32) < 0.1, axis=-1))  # 20 MB
    convert_npy_to_zarr(tmp_path / "big.npy", tmp_path / "big.zarr")
    edges = np.array([3, 400, 5000, 19_000])
    for config in (NpyCubeConfig(path=tmp_path / "big.npy", start=100, fix="none"),
                   ZarrCubeConfig(path=tmp_path / "big.zarr", start=100)):
        source = config.build()
        blob = pickle.dumps(source)
        assert len(blob) < 10_000, f"{config.plugin} pickles {len(blob)} bytes"
        again = pickle.loads(blob)
        assert again.config.layout == "packed"  # the detected layout travels: reopening samples no frames
        np.testing.assert_array_equal(again.sum_ranges(edges), source.sum_ranges(edges))


def test_swissspad_source_pickles_as_its_settings(tmp_path):
    from capture_helpers import simulate_raw_half
    from photonpano.plugins.sources._swissspad_readout import write_bin_files
    from photonpano.plugins.sources.swissspad import SwissSpadBinConfig

    _, raw = simulate_raw_half(1100, flux=0.3, speed_px_per_frame=0.05, vibration_px=1.0)
    write_bin_files(raw, tmp_path / "capture")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        source = SwissSpadBinConfig(path=tmp_path / "capture").build()
        blob = pickle.dumps(source)
        again = pickle.loads(blob)
    assert len(blob) < 10_000
    edges = np.array([0, 511, 513, 1100])
    np.testing.assert_array_equal(again.sum_ranges(edges), source.sum_ranges(edges))


def test_intensity_file_sources_pickle_as_their_settings(tmp_path):
    from pathlib import Path

    pytest.importorskip("av")
    pytest.importorskip("pyMRAW")
    from capture_helpers import write_video
    from photonpano.plugins.sources.photron import PhotronMrawConfig
    from photonpano.plugins.sources.video import VideoConfig

    frames = (np.random.default_rng(6).random((20, 32, 48)) * 255).astype(np.uint8)
    write_video(tmp_path / "rec.avi", frames, fps=30, codec="mjpeg", q=2)
    mraw = Path(__file__).parents[1] / "data" / "highspeed" / "ball_12bit.mraw"
    for config in (VideoConfig(path=tmp_path / "rec.avi"), PhotronMrawConfig(path=mraw)):
        source = config.build()
        edges = np.array([0, 3, 11])
        before = source.sum_ranges(edges)  # a decoder and its cache are open: still pickles as settings
        blob = pickle.dumps(source)
        assert len(blob) < 10_000, f"{config.plugin} pickles {len(blob)} bytes"
        np.testing.assert_array_equal(pickle.loads(blob).sum_ranges(edges), before)
