"""Output folders: atomic files, manifest, a safe --force, the lock, retries, OS errors."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from photonpano import outputs
from robust import TINY, assert_one_line_error, assert_sound_folder, digests, invoke


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A complete tiny demo run (copied by the tests that change it)."""
    out = tmp_path_factory.mktemp("finished") / "out"
    result = invoke("demo", "-o", out, *TINY)
    assert result.exit_code == 0, result.stderr
    return out


def _copy(folder, tmp_path):
    import shutil

    target = tmp_path / "out"
    shutil.copytree(folder, target)
    return target


def test_a_run_is_complete_and_lists_its_files(finished):
    assert assert_sound_folder(finished)
    manifest = json.loads((finished / "manifest.json").read_text())
    assert set(manifest["files"]) == {p.name for p in finished.iterdir()} - {"manifest.json"}
    assert manifest["files"][-1] == "run.json"
    assert not (finished / outputs.LOCK).exists() and not (finished / outputs.CHECKPOINTS).exists()


def test_output_is_a_file(tmp_path):
    (tmp_path / "out").write_text("mine")
    assert_one_line_error(invoke("demo", "-o", tmp_path / "out", *TINY), "out", "is not a folder")
    assert (tmp_path / "out").read_text() == "mine"


def test_output_parent_is_a_file(tmp_path):
    (tmp_path / "file").write_text("mine")
    assert_one_line_error(invoke("demo", "-o", tmp_path / "file" / "out", *TINY), "file/out", "cannot write")


def test_non_empty_folder_is_refused(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine")
    assert_one_line_error(invoke("demo", "-o", tmp_path / "out", *TINY), "not empty", "--force", "--resume")
    assert os.listdir(tmp_path / "out") == ["notes.txt"]


@pytest.mark.parametrize("name", ["capture.npy", "homographies.npy"])
def test_input_inside_the_output_folder_is_refused(tmp_path, small_cube, name):
    out = tmp_path / "out"
    out.mkdir()
    cube = out / name
    cube.write_bytes(small_cube.read_bytes())
    before = digests(out)
    for extra in ([], ["--force"]):
        assert_one_line_error(invoke("pano", cube, "-o", out, *extra), name, "inside the output folder")
    assert digests(out) == before


def test_force_replaces_exactly_the_previous_run(finished, tmp_path):
    out = _copy(finished, tmp_path)
    (out / "notes.txt").write_text("mine")
    assert (out / "panorama.png").exists()
    result = invoke("demo", "-o", out, "--force", *TINY, "--set", "outputs.panorama_png=false")
    assert result.exit_code == 0, result.stderr
    assert not (out / "panorama.png").exists()  # the old run's PNG does not linger
    assert (out / "notes.txt").read_text() == "mine"  # other files are kept
    assert assert_sound_folder(out)
    assert json.loads((out / "run.json").read_text())["spec"]["outputs"]["panorama_png"] is False


def test_failed_force_rerun_keeps_the_previous_run(finished, tmp_path, small_cube):
    out = _copy(finished, tmp_path)
    before = digests(out)
    bad = tmp_path / "bad.npy"
    bad.write_bytes(small_cube.read_bytes()[:300])
    assert_one_line_error(invoke("pano", bad, "-o", out, "--force"), "bad.npy", "truncated")
    assert digests(out) == before  # nothing removed, no new spec.yaml


def test_retry_after_a_failure_is_not_refused(tmp_path, small_cube):
    out = tmp_path / "out"
    assert_one_line_error(invoke("demo", "-o", out, *TINY, "--set", "group_size=100000"), "resampler")
    assert not out.exists()  # the failed run removed what it wrote
    out.mkdir()
    assert_one_line_error(invoke("demo", "-o", out, *TINY, "--set", "group_size=100000"), "resampler")
    assert out.is_dir() and not os.listdir(out)  # a folder the user made stays, empty
    result = invoke("demo", "-o", out, *TINY)
    assert result.exit_code == 0, result.stderr
    assert assert_sound_folder(out)


def test_a_live_lock_refuses_a_second_run(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / outputs.LOCK).write_text(f"{holder.pid} {__import__('socket').gethostname()}\n")
        assert_one_line_error(invoke("demo", "-o", out, *TINY), "in use by another run", str(holder.pid))
        assert os.listdir(out) == [outputs.LOCK]
    finally:
        holder.kill()
        holder.wait()


def test_a_stale_lock_is_taken_over(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / outputs.LOCK).write_text(f"{dead.pid} {__import__('socket').gethostname()}\n")
    (out / "manifest.json").write_text(json.dumps({"files": ["spec.yaml"], "complete": False}))
    result = invoke("demo", "-o", out, *TINY, "--force")
    assert result.exit_code == 0, result.stderr
    assert not (out / outputs.LOCK).exists() and assert_sound_folder(out)


def test_two_concurrent_runs_one_is_refused(tmp_path):
    from photonpano.outputs import RunFolder

    with RunFolder(tmp_path / "out"):
        assert_one_line_error(invoke("demo", "-o", tmp_path / "out", *TINY), "in use by another run")


@pytest.mark.parametrize("manifest", [
    {"files": ["../victim.txt", "/etc/hostname"], "complete": True},
    "not json {",
])
def test_a_hostile_manifest_cannot_remove_other_files(tmp_path, manifest):
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "victim.txt").write_text("keep")
    (out / "manifest.json").write_text(manifest if isinstance(manifest, str) else json.dumps(manifest))
    result = invoke("demo", "-o", out, *TINY, "--force")
    assert result.exit_code == 0, result.stderr
    assert (tmp_path / "victim.txt").read_text() == "keep"


@pytest.mark.parametrize("args, message", [
    ([], "holds no interrupted run"),
    (["complete"], "already complete"),
    (["other-spec"], "the spec differs"),
])
def test_resume_refusals(finished, tmp_path, args, message):
    out = tmp_path / "out"
    extra = []
    if args == ["complete"]:
        out = _copy(finished, tmp_path)
    elif args == ["other-spec"]:
        out = _copy(finished, tmp_path)
        (out / "run.json").unlink()
        extra = ["--set", "levels=1"]
    else:
        out.mkdir()
    assert_one_line_error(invoke("demo", "-o", out, *TINY, *extra, "--resume"), message)


@pytest.mark.parametrize("victim", ["homographies.npy", "panorama.png", "run.json", "manifest.json"])
def test_full_disk_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, victim):
    """An OS error on any output (here ENOSPC at the rename) names the path; the run's files are removed."""
    real = os.replace

    def full(src, dst):
        if os.path.basename(dst) == victim and (victim != "manifest.json" or os.path.exists(dst)):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", full)
    out = tmp_path / "out"
    assert_one_line_error(invoke("demo", "-o", out, *TINY), victim, "No space left on device")
    assert not out.exists() or not [p for p in out.rglob("*") if p.is_file()]


def test_simulate_cube_path_is_written_atomically(tmp_path, monkeypatch):
    from photonpano.plugins.sources import simulate

    def broken(*args, **kwargs):
        raise RuntimeError("killed while rendering")

    monkeypatch.setattr(simulate, "simulate_packed_frames", broken, raising=False)
    monkeypatch.setattr("photonpano.photons.simulate_packed_frames", broken)
    cube = tmp_path / "cube.npy"
    with pytest.raises(RuntimeError):
        simulate.SimulateConfig(frames=1000, height=32, width=64, cube_path=cube).build()
    assert not cube.exists() and not list(tmp_path.iterdir())
    monkeypatch.undo()
    source = simulate.SimulateConfig(frames=1000, height=32, width=64, cube_path=cube).build()
    assert np.array_equal(np.load(cube), source.cube)
