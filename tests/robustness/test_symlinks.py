"""Symbolic links and forged manifests: no writer touches anything outside its output folder."""

from __future__ import annotations

import hashlib
import json
import os
import shutil

import numpy as np
import pytest
from robust import TINY, assert_one_line_error, assert_sound_folder, digests, invoke


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A complete tiny demo run (copied by the tests that change it)."""
    out = tmp_path_factory.mktemp("finished") / "out"
    result = invoke("demo", "-o", out, *TINY, "--set", "levels=1")
    assert result.exit_code == 0, result.stderr
    return out


@pytest.fixture
def outside(tmp_path):
    """A folder beside the output folder holding a file no run may touch."""
    folder = tmp_path / "outside"
    folder.mkdir()
    (folder / "victim.txt").write_text("keep me")
    (folder / "panorama.png").write_text("not a png, and keep me")
    return folder


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_manifest_records_the_hash_of_every_file(finished):
    manifest = json.loads((finished / "manifest.json").read_text())
    assert set(manifest["sha256"]) == set(manifest["files"])
    for name, digest in manifest["sha256"].items():
        assert _sha(finished / name) == digest, name


@pytest.mark.parametrize("with_hash", [True, False])
def test_force_never_follows_a_link_named_in_a_forged_manifest(finished, tmp_path, outside, with_hash):
    """``link/victim.txt`` with ``link -> outside``: --force keeps the victim (with or without a hash)."""
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    (out / "link").symlink_to(outside, target_is_directory=True)
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["files"] += ["link/victim.txt", "link"]
    if with_hash:  # a forger can hash the victim: the link is refused all the same
        manifest["sha256"]["link/victim.txt"] = _sha(outside / "victim.txt")
    else:
        del manifest["sha256"]
    (out / "manifest.json").write_text(json.dumps(manifest))
    before = digests(outside)
    result = invoke("demo", "-o", out, "--force", *TINY, "--set", "levels=1")
    assert result.exit_code == 0, result.stderr
    assert digests(outside) == before
    assert (out / "link").is_symlink()  # the link itself is kept too: the run did not write it
    assert assert_sound_folder(out)
    assert "link/victim.txt" not in json.loads((out / "manifest.json").read_text())["files"]


def test_force_keeps_a_listed_file_whose_content_the_run_did_not_write(finished, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    (out / "notes.txt").write_text("mine")
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["files"].append("notes.txt")
    manifest["sha256"]["notes.txt"] = "0" * 64  # forged: not the file's hash
    (out / "manifest.json").write_text(json.dumps(manifest))
    result = invoke("demo", "-o", out, "--force", *TINY, "--set", "levels=1", "--set", "outputs.panorama_png=false")
    assert result.exit_code == 0, result.stderr
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "panorama.png").exists()  # the previous run's own file is removed
    assert assert_sound_folder(out)


def test_an_output_replaced_by_a_link_is_never_written_through(finished, tmp_path, outside):
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    (out / "panorama.png").unlink()
    (out / "panorama.png").symlink_to(outside / "panorama.png")
    before = digests(outside)
    result = invoke("demo", "-o", out, "--force", *TINY, "--set", "levels=1")
    assert result.exit_code == 0, result.stderr
    assert digests(outside) == before
    assert not (out / "panorama.png").is_symlink() and assert_sound_folder(out)


def test_a_linked_sub_folder_is_refused(tmp_path, outside):
    """``checkpoints -> outside``: the run refuses in one line instead of writing its checkpoints there."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoints").symlink_to(outside, target_is_directory=True)
    before = digests(outside)
    assert_one_line_error(invoke("demo", "-o", out, "--force", *TINY), out / "checkpoints", "symbolic link")
    assert digests(outside) == before and sorted(os.listdir(outside)) == ["panorama.png", "victim.txt"]


def test_a_linked_output_folder_is_refused(tmp_path, outside):
    link = tmp_path / "out"
    link.symlink_to(outside, target_is_directory=True)
    before = digests(outside)
    for extra in ([], ["--force"]):
        assert_one_line_error(invoke("demo", "-o", link, *extra, *TINY), link, "symbolic link")
    assert digests(outside) == before and sorted(os.listdir(outside)) == ["panorama.png", "victim.txt"]


def test_a_partial_name_planted_as_a_link_is_not_followed(tmp_path, outside, monkeypatch):
    """A link under the temporary name of an output is removed, never written through."""
    out = tmp_path / "out"
    out.mkdir()
    (out / f".partial-{os.getpid()}-homographies.npy").symlink_to(outside / "victim.txt")
    before = digests(outside)
    result = invoke("demo", "-o", out, "--force", *TINY, "--set", "levels=1")
    assert result.exit_code == 0, result.stderr
    assert digests(outside) == before
    assert np.load(out / "homographies.npy").ndim == 3


# -- convert: <out>.part is the conversion's own, or the conversion refuses -----------------------------------------

BIN_BYTES = 512 * 256 * 64
"""One SwissSPAD2 half-array readout file: 512 frames of 256x512 bits."""


@pytest.fixture
def readout(tmp_path):
    """A folder ``raw/`` with one random SwissSPAD2 readout file."""
    folder = tmp_path / "raw"
    folder.mkdir()
    (folder / "RAW00000.bin").write_bytes(np.random.default_rng(1).integers(0, 256, BIN_BYTES, np.uint8).tobytes())
    return folder


def _convert(*args):
    return invoke("convert", *args, "--no-check-layout")


def test_convert_refuses_a_part_file_linked_to_its_input(tmp_path, readout):
    """``<out>.part -> RAW00000.bin``: the input was overwritten; now the conversion refuses."""
    out = tmp_path / "cube.npy"
    part = tmp_path / "cube.npy.part"
    part.symlink_to(readout / "RAW00000.bin")
    before = digests(readout)
    assert_one_line_error(_convert(readout, "-o", out), part, "symbolic link", "not written by this conversion")
    assert digests(readout) == before and not out.exists() and part.is_symlink()


@pytest.mark.parametrize("kind", ["file", "folder", "dangling link"])
def test_convert_refuses_a_part_path_it_did_not_create(tmp_path, readout, kind):
    out = tmp_path / "cube.npy"
    part = tmp_path / "cube.npy.part"
    if kind == "file":
        part.write_text("someone's file")
    elif kind == "folder":
        part.mkdir()
        (part / "keep.txt").write_text("keep")
    else:
        part.symlink_to(tmp_path / "nowhere")
    before = digests(tmp_path)
    assert_one_line_error(_convert(readout, "-o", out), part, "not written by this conversion")
    assert digests(tmp_path) == before and not out.exists() and not (tmp_path / "nowhere").exists()


def test_convert_refuses_a_linked_output(tmp_path, readout):
    out = tmp_path / "cube.npy"
    out.symlink_to(tmp_path / "elsewhere.npy")  # dangling: exists() is False
    assert_one_line_error(_convert(readout, "-o", out), out)
    assert not (tmp_path / "elsewhere.npy").exists() and out.is_symlink()


def test_convert_npy_to_zarr_refuses_a_part_linked_to_a_folder(tmp_path, small_cube):
    """``<out>.zarr.part -> unrelated folder``: a traceback before; now one line, the folder untouched."""
    unrelated = tmp_path / "unrelated"
    unrelated.mkdir()
    (unrelated / "data.txt").write_text("keep")
    part = tmp_path / "cube.zarr.part"
    part.symlink_to(unrelated, target_is_directory=True)
    before = digests(unrelated, small_cube)
    assert_one_line_error(invoke("convert", small_cube, "-o", tmp_path / "cube.zarr"), part, "symbolic link")
    assert digests(unrelated, small_cube) == before and not (tmp_path / "cube.zarr").exists()


def test_convert_leaves_nothing_behind_and_writes_the_cube(tmp_path, readout):
    out = tmp_path / "cube.npy"
    result = _convert(readout, "-o", out)
    assert result.exit_code == 0, result.stderr
    assert np.load(out).shape == (512, 256, 64)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.npy", "raw"]


def test_compare_refuses_a_linked_output_folder(tmp_path, outside):
    link = tmp_path / "cmp"
    link.symlink_to(outside, target_is_directory=True)
    before = digests(outside)
    for extra in ([], ["--force"]):
        assert_one_line_error(invoke("compare", "simulate", "-o", link, "-l", "opencv-orb", *extra, *TINY),
                              link, "symbolic link")
    assert digests(outside) == before


def test_compare_never_writes_through_a_linked_locator_folder(tmp_path, outside):
    out = tmp_path / "cmp"
    out.mkdir()
    (out / "opencv-orb").symlink_to(outside, target_is_directory=True)
    before = digests(outside)
    result = invoke("compare", "simulate", "-o", out, "-l", "opencv-orb", "--force", *TINY, "--set", "levels=1")
    assert_one_line_error(result, out / "opencv-orb", "symbolic link")
    assert digests(outside) == before and not (outside / "homographies.npy").exists()


def test_pose_refuses_a_linked_output_folder(tmp_path, outside):
    from photonpano.errors import OutputError
    from photonpano.host import PluginHost
    from photonpano.pose_run import run_pose
    from photonpano.spec import validate_spec

    link = tmp_path / "pose"
    link.symlink_to(outside, target_is_directory=True)
    spec = validate_spec({"source": {"plugin": "simulate", "frames": 100, "height": 32, "width": 64},
                          "pose_estimator": {"plugin": "pycolmap-sfm"}}, PluginHost())
    before = digests(outside)
    with pytest.raises(OutputError, match=f"output folder {link} is a symbolic link"):
        run_pose(spec, link, None, force=True)
    assert digests(outside) == before


def test_batch_refuses_a_linked_output_folder_and_a_linked_capture_folder(tmp_path, outside):
    link = tmp_path / "batch"
    link.symlink_to(outside, target_is_directory=True)
    before = digests(outside)
    assert_one_line_error(invoke("batch", "simulate", "-o", link, *TINY), link, "symbolic link")
    out = tmp_path / "real"
    out.mkdir()
    (out / "simulate").symlink_to(outside, target_is_directory=True)  # the capture's own folder
    result = invoke("batch", "simulate", "-o", out, "--force", *TINY, "--set", "levels=1")
    assert result.exit_code == 1 and "symbolic link" in result.stdout + result.stderr
    assert digests(outside) == before and sorted(os.listdir(outside)) == ["panorama.png", "victim.txt"]


def test_convert_zarr_to_npy_refuses_a_part_linked_to_an_input(tmp_path, small_cube):
    pytest.importorskip("zarr")
    from photonpano.plugins.sources.zarr_cube import convert_npy_to_zarr

    cube = tmp_path / "cube.zarr"
    convert_npy_to_zarr(small_cube, cube)
    part = tmp_path / "back.npy.part"
    part.symlink_to(small_cube)
    before = digests(small_cube, cube)
    assert_one_line_error(invoke("convert", cube, "-o", tmp_path / "back.npy"), part, "symbolic link")
    assert digests(small_cube, cube) == before and not (tmp_path / "back.npy").exists()


def test_a_plugin_failure_log_is_never_written_through_a_planted_link(tmp_path, monkeypatch):
    """The traceback log in the shared temp folder has a fresh unique name: a link planted there is left alone."""
    import tempfile

    from photonpano.faults import plugin_failure
    from photonpano.host import PluginHost

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / f"photonpano-{os.getpid()}-traceback.log").symlink_to(victim)  # the old, predictable name
    try:
        raise RuntimeError("boom")
    except RuntimeError as exc:
        message = str(plugin_failure(exc, PluginHost(autoload=False)))
    log = message.split("traceback in ")[1].split(";")[0]
    assert victim.read_text() == "keep"
    assert "RuntimeError: boom" in open(log).read() and not os.path.islink(log)
