"""A full disk, a full standard output, a full log file: one line naming the path, exit 1, nothing partial."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from robust import TINY, assert_one_line_error, digests, invoke

FULL = "/dev/full"

pytestmark = pytest.mark.skipif(not os.path.exists(FULL), reason="needs /dev/full (Linux)")


def _cli(*args, stdout=subprocess.PIPE, code: str | None = None, timeout: float = 120):
    """Run the ``photonpano`` entry point (``main``) in a subprocess, optionally after ``code``."""
    prelude = textwrap.dedent(code or "")
    script = (f"import sys\n{prelude}\nfrom photonpano.cli import main\n"
              "sys.argv = ['photonpano', *sys.argv[1:]]\nmain()\n")
    return subprocess.run([sys.executable, "-c", script, *map(str, args)], stdout=stdout, stderr=subprocess.PIPE,
                          text=True, timeout=timeout)


def _one_line(result, *culprits):
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
    lines = [line for line in result.stderr.strip().splitlines() if not line.startswith("warning:")]
    assert "Traceback" not in result.stderr and "Logging error" not in result.stderr, result.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr[-2000:]
    for culprit in culprits:
        assert culprit in lines[0], (culprit, lines[0])
    return lines[0]


@pytest.mark.parametrize("args", [["plugins"], ["--version"], ["schema"]])
def test_standard_output_on_a_full_device(args):
    with open(FULL, "w") as full:
        result = _cli(*args, stdout=full)
    _one_line(result, "standard output", FULL, "No space left on device")


def test_log_file_on_a_full_device_is_refused_before_any_work(tmp_path):
    out = tmp_path / "out"
    result = _cli("-q", "--log-file", FULL, "demo", "-o", out, *TINY)
    _one_line(result, f"--log-file {FULL}", "No space left on device")
    assert not out.exists()


def test_log_file_filling_up_during_a_run_is_one_line_and_exit_1(tmp_path):
    """The disk fills after the header line: one line (not logging's traceback dump), logging stops, exit 1."""
    patch = """
        import errno
        from photonpano.cli_io import LogFileHandler

        calls = []

        def flush(self):
            calls.append(1)
            if len(calls) > 2:
                raise OSError(errno.ENOSPC, "No space left on device")

        LogFileHandler.flush = flush
    """
    log = tmp_path / "run.log"
    result = _cli("-q", "--log-file", log, "demo", "-o", tmp_path / "out", *TINY, "--set", "levels=1", code=patch)
    _one_line(result, f"--log-file {log}", "No space left on device", "logging to it stopped")
    assert (tmp_path / "out" / "run.json").is_file()  # the run itself completed


def test_compare_into_a_full_disk(tmp_path, monkeypatch):
    real = os.replace

    def full(src, dst):
        if os.path.basename(dst) == "compare.json":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", full)
    out = tmp_path / "cmp"
    line = assert_one_line_error(invoke("compare", "simulate", "-o", out, "-l", "opencv-orb", *TINY,
                                        "--set", "levels=1"), out / "compare.json", "No space left on device")
    assert "free there" in line
    assert not (out / "compare.json").exists()
    assert not [p for p in out.rglob("*") if p.name.startswith(".partial-")]


@pytest.mark.parametrize("stage", ["write", "rename"])
def test_convert_into_a_full_disk(tmp_path, small_cube, monkeypatch, stage):
    """ENOSPC while writing or renaming the cube: one line naming it and the space needed; no cube, no .part."""
    from photonpano import streaming

    out = tmp_path / "cube.npy"
    real_replace, real_fdopen = os.replace, os.fdopen

    class FullFile:
        def __init__(self, handle):
            self.handle = handle

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    if stage == "write":
        monkeypatch.setattr(streaming.os, "fdopen", lambda fd, mode: FullFile(real_fdopen(fd, mode)))
    else:
        monkeypatch.setattr(os, "replace", lambda src, dst: (_ for _ in ()).throw(
            OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))) if str(dst) == str(out) else real_replace(src, dst))
    before = digests(small_cube)
    # a zarr cube converts to .npy through the same writer; without zarr, test it directly
    with pytest.raises(Exception) as info:
        streaming.write_npy_blocks(out, (400, 32, 8), np.uint8, iter([np.load(small_cube)]))
    assert type(info.value).__name__ == "OutputError"
    message = str(info.value)
    assert str(out) in message and "No space left on device" in message and "needed" in message
    assert "\n" not in message
    assert not out.exists() and not (tmp_path / "cube.npy.part").exists()
    assert digests(small_cube) == before


def test_a_read_error_of_an_input_is_not_blamed_on_the_output(tmp_path):
    from photonpano import streaming

    def blocks():
        yield np.zeros((10, 4, 2), np.uint8)
        raise OSError("/data/RAW00001.bin: short read (0 of 8388608 bytes)")

    with pytest.raises(OSError, match="RAW00001.bin: short read"):
        streaming.write_npy_blocks(tmp_path / "c.npy", (20, 4, 2), np.uint8, blocks())
    assert not list(tmp_path.iterdir())
