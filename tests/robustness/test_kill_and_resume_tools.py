"""compare, batch and convert killed at any moment: nothing complete-looking, --resume equals an uninterrupted run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from robust import assert_one_line_error, assert_sound_folder, digests, invoke, run_subprocess

COMPARE_SPEC = """\
source: {plugin: simulate, frames: 1500, height: 96, width: 200, flux: 0.5, vibration_px: 2.0}
group_size: 250
levels: 2
pair_offsets: [1, 2]
"""
LOCATORS = "opencv-orb,opencv-orb:max_features=1000,opencv-orb:levels=2"
NAMES = ["opencv-orb", "opencv-orb_max_features=1000", "opencv-orb_levels=2"]
VOLATILE = ("total_s", "locate_s", "timings_s", "cache")
"""Row fields that differ between any two runs: wall times, and feature-cache counts (the cache is shared by the
locators run in one process, so a resumed comparison, which skips some, counts other hits)."""


def _without_times(value):
    if isinstance(value, dict):
        return {k: _without_times(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [_without_times(v) for v in value]
    return value


def _compare_outputs(out: Path) -> tuple[dict[str, np.ndarray], list]:
    runs = json.loads((out / "compare.json").read_text())["runs"]
    return {name: np.load(out / name / "homographies.npy") for name in NAMES}, _without_times(runs)


def _assert_files_complete(out: Path, skip: str | None = None) -> None:
    """Every file under a final name in ``out`` (but those under a folder named ``skip``) loads completely."""
    for path in out.rglob("*"):
        if path.is_file() and not path.name.startswith(".partial-") and skip not in path.relative_to(out).parts:
            if path.suffix == ".npy":
                np.load(path, allow_pickle=False)
            elif path.suffix == ".npz":
                with np.load(path, allow_pickle=False) as data:
                    [data[k] for k in data.files]
            elif path.suffix == ".json":
                json.loads(path.read_text())
            elif path.suffix == ".ply":
                head, _, body = path.read_bytes().partition(b"end_header\n")
                count = int(head.split(b"element vertex ")[1].split()[0])
                assert len(body) == 15 * count, path  # 3 float32 and 3 uint8 per point


def _assert_compare_sound(out: Path) -> bool:
    """Every file under a final name is complete; compare.json only with a complete manifest. Returns complete."""
    if not out.exists():
        return False
    _assert_files_complete(out)
    if not (out / "compare.json").exists():
        return False
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] is True and all((out / name).is_file() for name in manifest["files"])
    assert not (out / "checkpoints").exists()
    return True


@pytest.fixture(scope="module")
def compare_reference(tmp_path_factory):
    """The spec file, an uninterrupted comparison's homographies and rows, and its wall time in seconds."""
    folder = tmp_path_factory.mktemp("compare-reference")
    spec = folder / "spec.yaml"
    spec.write_text(COMPARE_SPEC)
    start = time.perf_counter()
    result = run_subprocess("compare", spec, "-o", folder / "out", "-l", LOCATORS)
    assert result.returncode == 0, result.stderr
    return spec, *_compare_outputs(folder / "out"), time.perf_counter() - start


def _assert_same_comparison(out: Path, reference) -> None:
    homographies, rows = _compare_outputs(out)
    assert rows == reference[2]
    for name in NAMES:
        assert np.array_equal(homographies[name], reference[1][name]), name


def test_compare_interrupted_after_a_locator_resumes_the_others_only(compare_reference, tmp_path, monkeypatch):
    from photonpano import compare

    spec = compare_reference[0]
    cache_row = compare._cache_row

    def interrupt(folder, index, key, row, homographies):
        cache_row(folder, index, key, row, homographies)
        if index == 0:
            raise KeyboardInterrupt

    monkeypatch.setattr(compare, "_cache_row", interrupt)
    out = tmp_path / "out"
    before = digests(spec)
    assert invoke("compare", spec, "-o", out, "-l", LOCATORS).exit_code != 0
    assert not _assert_compare_sound(out) and not (out / ".photonpano.lock").exists()
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["locator_0.npz"]
    assert_one_line_error(invoke("compare", spec, "-o", out, "-l", LOCATORS), out, "--resume")
    monkeypatch.setattr(compare, "_cache_row", cache_row)
    ran = []
    compare_one = compare._compare_one
    monkeypatch.setattr(compare, "_compare_one", lambda item, *a: ran.append(item) or compare_one(item, *a))
    result = invoke("compare", spec, "-o", out, "-l", LOCATORS, "--resume")
    assert result.exit_code == 0, result.stderr
    assert ran == LOCATORS.split(",")[1:]  # the first locator's results were reused
    assert _assert_compare_sound(out)
    _assert_same_comparison(out, compare_reference)
    assert digests(spec) == before
    assert_one_line_error(invoke("compare", spec, "-o", out, "-l", LOCATORS, "--resume"), "already complete")


def test_compare_resume_refuses_another_locator_list(compare_reference, tmp_path, monkeypatch):
    from photonpano import compare

    def interrupt(folder, index, key, row, homographies):
        raise KeyboardInterrupt

    cache_row = compare._cache_row
    monkeypatch.setattr(compare, "_cache_row", lambda *a: (cache_row(*a), interrupt(*a)))
    out = tmp_path / "out"
    assert invoke("compare", compare_reference[0], "-o", out, "-l", "opencv-orb").exit_code != 0
    monkeypatch.setattr(compare, "_cache_row", cache_row)
    result = invoke("compare", compare_reference[0], "-o", out, "-l", "opencv-orb:levels=2", "--resume")
    assert_one_line_error(result, out / "checkpoints" / "locator_0.npz", "another spec or locator list")


@pytest.mark.slow
def test_compare_killed_at_random_moments_then_resumed(compare_reference, tmp_path):
    spec, _, _, duration = compare_reference
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("keep")
    before = digests(spec, outside)
    moments = [duration * f for f in (0.15, 0.35, 0.55, 0.75, 0.95)]
    for k, moment in enumerate(moments + [None]):
        out = tmp_path / f"kill{k}"
        process = subprocess.Popen([sys.executable, "-m", "photonpano.cli", "-q", "compare", str(spec), "-o",
                                    str(out), "-l", LOCATORS], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if moment is None:  # right after the first locator's results are cached
            while not (out / "checkpoints" / "locator_0.npz").exists() and process.poll() is None:
                time.sleep(0.01)
        else:
            time.sleep(moment)
        process.send_signal(signal.SIGKILL)
        process.wait()
        if not _assert_compare_sound(out):
            resume = ["--resume"] if (out / "manifest.json").exists() else []
            result = run_subprocess("compare", spec, "-o", out, "-l", LOCATORS, *resume)
            assert result.returncode == 0, (k, result.stderr)
            assert _assert_compare_sound(out)
        _assert_same_comparison(out, compare_reference)
    assert digests(spec, outside) == before


# -- batch ---------------------------------------------------------------------------------------------------------

BATCH_SPEC = """\
source: {{plugin: simulate, frames: 3000, height: 96, width: 200, flux: {flux}, vibration_px: 2.0}}
group_size: 250
levels: 3
outputs: {{trajectory_plot: false, report: false}}
"""


def _process_ended(pid: int, timeout_s: float) -> bool:
    from photonpano.outputs.disk import is_zombie

    end = time.perf_counter() + timeout_s
    while time.perf_counter() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        if is_zombie(pid):
            return True
        time.sleep(0.05)
    return False


@pytest.fixture(scope="module")
def batch_reference(tmp_path_factory):
    """Two spec files and the homographies of an uninterrupted batch of them, by capture name."""
    folder = tmp_path_factory.mktemp("batch-reference")
    specs = []
    for name, flux in (("a", 0.5), ("b", 0.3)):
        specs.append(folder / f"{name}.yaml")
        specs[-1].write_text(BATCH_SPEC.format(flux=flux))
    result = run_subprocess("batch", *specs, "-o", folder / "out", "--set", "workers=2")
    assert result.returncode == 0, result.stderr
    return specs, {name: np.load(folder / "out" / name / "homographies.npy") for name in ("a", "b")}


@pytest.mark.slow
@pytest.mark.parametrize("when", ["level_1", "level_2"])
def test_batch_killed_mid_capture_then_resumed(batch_reference, tmp_path, when):
    """SIGKILL once a capture has a checkpoint: the workers end too; --resume equals an uninterrupted batch."""
    specs, expected = batch_reference
    before = digests(*specs)
    out = tmp_path / "out"
    process = subprocess.Popen([sys.executable, "-m", "photonpano.cli", "-q", "batch", *map(str, specs), "-o",
                                str(out), "--set", "workers=2"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not list(out.glob(f"*/checkpoints/{when}.npz")) and process.poll() is None:
        time.sleep(0.01)
    holders = [int(lock.read_text().split()[0]) for lock in out.glob("*/.photonpano.lock")]
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert holders and all(_process_ended(pid, 10.0) for pid in holders)  # no orphan goes on writing
    complete = {name: assert_sound_folder(out / name) for name in ("a", "b")}
    assert not all(complete.values())
    result = run_subprocess("batch", *specs, "-o", out, "--resume", "--set", "workers=2")
    assert result.returncode == 0, result.stderr
    for name in ("a", "b"):
        assert assert_sound_folder(out / name)
        assert np.array_equal(np.load(out / name / "homographies.npy"), expected[name]), name
        assert (f"{name} ok (reused)" in " ".join(result.stdout.split())) == complete[name]
    finished = digests(out)
    result = run_subprocess("batch", *specs, "-o", out, "--resume")  # nothing left to do
    assert result.returncode == 0 and result.stdout.count("(reused)") == 2, result.stdout
    assert digests(out) == finished and digests(*specs) == before


def test_batch_resume_and_force_exclude_each_other(tmp_path):
    assert_one_line_error(invoke("batch", "simulate", "-o", tmp_path / "o", "--resume", "--force"), "--resume")


def test_capture_state_never_follows_links(tmp_path):
    from photonpano.batch import capture_state

    real = tmp_path / "real"
    real.mkdir()
    assert capture_state(real) == "new"
    (real / "manifest.json").write_text("{}")
    assert capture_state(real) == "interrupted"
    (real / "run.json").write_text("{}")
    assert capture_state(real) == "complete"
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    assert capture_state(link) == "new"  # the run refuses the linked folder itself


def test_batch_workers_exit_with_their_parent(tmp_path):
    """The initializer of the batch's workers ends a process whose parent was killed."""
    script = textwrap.dedent("""
        import subprocess, sys, time
        child = subprocess.Popen([sys.executable, "-c",
            "import os, time; from photonpano.batch import exit_with_parent; "
            "exit_with_parent(os.getppid(), 0.05); print(os.getpid(), flush=True); time.sleep(60)"],
            stdout=subprocess.PIPE, text=True)
        print(child.stdout.readline().strip(), flush=True)
        time.sleep(60)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    parent.kill()
    parent.wait()
    assert _process_ended(worker, 10.0)


# -- convert ---------------------------------------------------------------------------------------------------------

BIN_BYTES = 512 * 256 * 64
"""One SwissSPAD2 half-array readout file: 512 frames of 256x512 bits."""

KILLING_CONVERT = """
import os, signal, sys
from pathlib import Path

kind, source, output, k = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
calls = []


def progress(done, total):
    calls.append(done)
    if len(calls) == k:
        os.kill(os.getpid(), signal.SIGKILL)


if kind == "bin":
    from photonpano.plugins.sources.swissspad import convert_bin_to_npy

    convert_bin_to_npy([source], output, "half", check_layout=False, chunk_mb=1, progress=progress)
else:
    from photonpano.plugins.sources.zarr_cube import convert_npy_to_zarr

    convert_npy_to_zarr(source, output, chunk_bytes=50 * 256, progress=progress)
"""


def _killed_convert(kind: str, source: Path, output: Path, k: int) -> int:
    return subprocess.run([sys.executable, "-c", KILLING_CONVERT, kind, str(source), str(output), str(k)],
                          capture_output=True, timeout=300).returncode


def _tree_digest(root: Path) -> dict[str, str]:
    return {str(Path(p).relative_to(root)): h for p, h in digests(root).items()}


@pytest.mark.parametrize("kind", ["bin", "zarr"])
def test_convert_killed_at_several_moments_then_resumed(tmp_path, small_cube, kind):
    """Killed after 1, half or all blocks (before the rename): no output; --resume writes it byte-identically."""
    if kind == "zarr":
        pytest.importorskip("zarr")
        source, name, blocks = small_cube, "cube.zarr", 8  # 400 frames in chunks of 50
    else:
        source = tmp_path / "raw"
        source.mkdir()
        (source / "RAW00000.bin").write_bytes(np.random.default_rng(1).integers(0, 256, BIN_BYTES, np.uint8)
                                              .tobytes())
        name, blocks = "cube.npy", 8  # 512 frames of 16 KiB in 1 MiB reads
    work = tmp_path / "work"
    work.mkdir()
    before = digests(source)
    extra = [] if kind == "zarr" else ["--no-check-layout"]
    (tmp_path / "reference").mkdir()
    reference = tmp_path / "reference" / name
    assert invoke("convert", source, "-o", reference, *extra).exit_code == 0  # uninterrupted
    expected = _tree_digest(reference) if reference.is_dir() else digests(reference)[str(reference)]
    for k in (1, blocks // 2, blocks):
        output = work / f"{k}-{name}"
        assert _killed_convert(kind, source, output, k) == -signal.SIGKILL
        part = output.with_name(output.name + ".part")
        assert not output.exists() and part.exists() and output.with_name(output.name + ".part.owner").is_file()
        assert_one_line_error(invoke("convert", source, "-o", output, *extra), part, "interrupted", "--resume")
        result = invoke("convert", source, "-o", output, "--resume", *extra)
        assert result.exit_code == 0, result.stderr
        got = _tree_digest(output) if output.is_dir() else digests(output)[str(output)]
        assert got == expected, k
        assert sorted(p.name for p in work.iterdir() if p.name.startswith(f"{k}-")) == [output.name]
    assert digests(source) == before


def test_convert_resume_refuses_a_part_it_does_not_own(tmp_path, small_cube):
    """--resume removes only a .part recorded by a conversion whose process has ended."""
    pytest.importorskip("zarr")
    out = tmp_path / "cube.zarr"
    part, owner = tmp_path / "cube.zarr.part", tmp_path / "cube.zarr.part.owner"
    part.mkdir()
    (part / "keep.txt").write_text("someone's file")
    before = digests(tmp_path)
    assert_one_line_error(invoke("convert", small_cube, "-o", out, "--resume"), part, "not written by this conversion")
    assert digests(tmp_path) == before
    owner.write_text(f"{os.getpid()} {os.uname().nodename}\n")  # a conversion still running (this process)
    before = digests(tmp_path)
    assert_one_line_error(invoke("convert", small_cube, "-o", out, "--resume"), part, "another conversion")
    assert digests(tmp_path) == before
    owner.unlink()
    owner.symlink_to(small_cube)
    before = digests(tmp_path)
    assert_one_line_error(invoke("convert", small_cube, "-o", out, "--resume"), owner, "symbolic link")
    assert digests(tmp_path) == before and owner.is_symlink() and not out.exists()


# -- pose ------------------------------------------------------------------------------------------------------------

POSE = ["pose", "simulate3d", "--set", "source.height=128", "--set", "source.width=248", "--set",
        "source.focal_px=210", "--set", "pose_estimator.group_size=500", "--set", "source.frames=3000", "--set",
        "pose_estimator.levels=3"]
"""A small pose run (three levels, about 20 s on two busy cores)."""


def _pose_sound(out: Path) -> bool:
    """Every file under a final name is complete; run.json only with a complete manifest. Returns complete."""
    if not out.exists():
        return False
    _assert_files_complete(out, skip="work")
    if not (out / "run.json").exists():
        return False
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] is True and all((out / name).is_file() for name in manifest["files"])
    assert not (out / "checkpoints").exists() and not (out / ".photonpano.lock").exists()
    return True


def _checkpointed(out: Path) -> tuple[list[dict], dict[str, np.ndarray]]:
    """The level rows and arrays of the latest pose checkpoint in ``out`` (empty when none)."""
    found = sorted(out.glob("checkpoints/pose_*.npz"), key=lambda p: int(p.stem.split("_")[1]))
    for path in reversed(found):
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(data["meta"].tobytes().decode())
                return meta["record"]["levels"], {k: data[k] for k in data.files if k != "meta"}
        except (OSError, ValueError, KeyError, EOFError):  # written when the kill came: the one before counts
            continue
    return [], {}


def _assert_reused(out: Path, rows: list[dict], arrays: dict[str, np.ndarray]) -> None:
    """The finished run in ``out`` kept the checkpointed levels' figures and poses bit for bit."""
    levels = json.loads((out / "run.json").read_text())["levels"]
    for saved, row in zip(rows, levels):
        assert {k: v for k, v in row.items() if k in saved and k != "timings_s"} == \
            {k: v for k, v in saved.items() if k != "timings_s"}, row["level"]
    if rows and len(levels) == len(rows):  # killed after the last level: the result is the checkpoint's
        assert np.array_equal(np.load(out / "exposure_poses.npy"), arrays[f"array_poses_{len(rows) - 1}"],
                              equal_nan=True)


def test_pose_interrupted_after_level_1_resumes_without_mapping_again(tmp_path, monkeypatch):
    pytest.importorskip("pycolmap")
    from photonpano.plugins.pose import pycolmap_sfm
    from photonpano.pose_checkpoints import PoseCheckpoints

    save = PoseCheckpoints.save

    def interrupt(self, level, *args, **kwargs):
        save(self, level, *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(PoseCheckpoints, "save", interrupt)
    out = tmp_path / "out"
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("keep")
    before = digests(outside)
    assert invoke(*POSE, "-o", out).exit_code != 0
    assert not _pose_sound(out) and not (out / ".photonpano.lock").exists()
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["pose_1", "pose_1.npz"]
    rows, arrays = _checkpointed(out)
    assert [row["level"] for row in rows] == [1]
    assert_one_line_error(invoke(*POSE, "-o", out), out, "--resume")  # not over an interrupted run unasked
    assert_one_line_error(invoke(*POSE, "-o", out, "--resume", "--set", "pose_estimator.levels=2"),
                          "the spec differs")
    monkeypatch.setattr(PoseCheckpoints, "save", save)
    mapped = []
    monkeypatch.setattr(pycolmap_sfm, "map_exposures", lambda *a: mapped.append(a))  # level 1 is not redone
    result = invoke(*POSE, "-o", out, "--resume")
    assert result.exit_code == 0, result.stderr
    assert not mapped and _pose_sound(out)
    _assert_reused(out, rows, arrays)
    assert digests(outside) == before
    assert_one_line_error(invoke(*POSE, "-o", out, "--resume"), "already complete")
    assert_one_line_error(invoke(*POSE, "-o", out, "--resume", "--force"), "exclude each other")


@pytest.mark.slow
def test_pose_killed_at_random_moments_then_resumed(tmp_path):
    """SIGKILL after level 1's checkpoint and at fractions of a run: --resume completes, reusing what was saved.

    And equals the uninterrupted run (the reference) bit for bit.
    """
    pytest.importorskip("pycolmap")
    start = time.perf_counter()
    reference = run_subprocess(*POSE, "-o", tmp_path / "reference")
    duration = time.perf_counter() - start
    assert reference.returncode == 0, reference.stderr
    for k, moment in enumerate([None, *(duration * f for f in (0.3, 0.6, 0.9))]):
        out = tmp_path / f"kill{k}"
        process = subprocess.Popen([sys.executable, "-m", "photonpano.cli", "-q", *POSE, "-o", str(out)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if moment is None:  # right after level 1's checkpoint
            while not (out / "checkpoints" / "pose_1.npz").exists() and process.poll() is None:
                time.sleep(0.01)
        else:
            time.sleep(moment)
        process.send_signal(signal.SIGKILL)
        process.wait()
        if _pose_sound(out):
            continue  # it had finished
        rows, arrays = _checkpointed(out)
        if moment is None:
            assert [row["level"] for row in rows] == [1]
        resume = ["--resume"] if (out / "manifest.json").exists() else []
        result = run_subprocess(*POSE, "-o", out, *resume)
        assert result.returncode == 0, (k, result.stderr)
        assert _pose_sound(out)
        _assert_reused(out, rows, arrays)
        # COLMAP runs single-threaded (plugins/pose/_colmap.py THREADS): the resumed run equals the uninterrupted one
        poses = np.load(out / "exposure_poses.npy")
        assert np.array_equal(poses, np.load(tmp_path / "reference" / "exposure_poses.npy"), equal_nan=True), k
        assert [row.get("registered") for row in json.loads((out / "run.json").read_text())["levels"]] == \
            [row.get("registered") for row in json.loads((tmp_path / "reference" / "run.json").read_text())["levels"]]
