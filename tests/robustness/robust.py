"""Helpers of the hostile-input suite: run the CLI, check one-line errors and output folders."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
from photonpano.cli import app
from typer.testing import CliRunner

TINY = ["--set", "source.frames=1500", "--set", "source.height=96", "--set", "source.width=200",
        "--set", "group_size=250", "--set", "levels=2", "--set", "pair_offsets=[1, 2]",
        "--set", "outputs.trajectory_plot=false", "--set", "outputs.report=false"]
"""A demo small enough for a test (about a second)."""

SMALL_SPEC = """\
source: {plugin: simulate, frames: 3000, height: 96, width: 200, flux: 0.5, vibration_px: 2.0}
group_size: 250
levels: 3
outputs: {trajectory_plot: false, report: false}
"""
"""The run of the kill and resume tests: three levels (the later two against the panorama)."""

COMPILED_AT_FIRST_CALL = """
@numba.njit(cache=False)
def kernel(x):
    total = 0.0
    for i in range(x.shape[0]):
        total += x[i] ** 2 if i % 3 else x[i]
    return total
"""
"""A numba kernel that compiles at its first call (about 0.3 s), for scripts that interrupt a compile."""


def invoke(*args):
    """Run the command line in this process with ``-q``; return click's result.

    With ``-q`` stderr holds only warnings and errors (no progress display); the result
    has ``exit_code`` and ``stderr``.
    """
    return CliRunner().invoke(app, ["-q", *(str(a) for a in args)])


def sigint_as(disposition: signal.Handlers = signal.SIG_DFL):
    """A ``preexec_fn`` that gives a child process ``SIGINT`` as ``disposition``, whatever the test runner's is.

    A child inherits an ignored ``SIGINT``: pytest started as a background job of a
    non-interactive shell (``pytest ... &``) has it ignored, and so would every command it
    starts, so a test sending Ctrl-C to a child, or one that expects the child to behave
    as in a terminal, sets it explicitly (``signal.SIG_DFL``: Python installs its
    ``KeyboardInterrupt`` handler; ``signal.SIG_IGN``: as in such a background job).
    """
    return lambda: signal.signal(signal.SIGINT, disposition)


def run_subprocess(*args, env: dict[str, str] | None = None, timeout: float = 300,
                   sigint: signal.Handlers = signal.SIG_DFL):
    """Run ``python -m photonpano.cli -q`` as a user would; ``returncode``, ``stdout``, ``stderr``.

    ``sigint``: the child's ``SIGINT`` disposition (see :func:`sigint_as`); by default as
    in a terminal, whatever pytest's.
    """
    return subprocess.run([sys.executable, "-m", "photonpano.cli", "-q", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, **(env or {})},
                          preexec_fn=sigint_as(sigint))


def digests(*paths: Path) -> dict[str, str]:
    """sha256 of every file under ``paths`` (files or folders)."""
    out = {}
    for root in paths:
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def assert_one_line_error(result, *culprits: object) -> str:
    """Exit code 1, no traceback, one line starting ``error:`` that names every culprit."""
    code = getattr(result, "exit_code", getattr(result, "returncode", None))
    err = result.stderr.strip()
    assert code == 1, (code, result.stdout[-2000:], err[-2000:])
    assert "Traceback" not in result.stdout + result.stderr
    lines = [line for line in err.splitlines() if not line.startswith("warning:")]
    assert len(lines) == 1, err[:2000]
    assert lines[0].startswith("error: ") and len(lines[0]) < 700, lines[0][:2000]
    for culprit in culprits:
        assert str(culprit) in lines[0], (culprit, lines[0])
    return lines[0]


def assert_sound_folder(folder: Path) -> bool:
    """No partial file under a final name; with run.json, a complete loadable run. Returns complete."""
    if not folder.exists():
        return False
    names = [p for p in folder.rglob("*") if p.is_file()]
    final = [p for p in names if not p.name.startswith(".partial-")]
    for path in final:  # every file under a final name is complete
        if path.suffix == ".npy":
            np.load(path, allow_pickle=False)
        elif path.suffix == ".png":
            assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None, path
        elif path.suffix == ".json":
            json.loads(path.read_text())
        elif path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                [data[k] for k in data.files]
    if not (folder / "run.json").exists():
        return False
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["complete"] is True
    for name in manifest["files"]:
        assert (folder / name).is_file(), name
    assert not [p for p in names if p.name.startswith(".partial-")]
    json.loads((folder / "run.json").read_text())["panorama"]
    homographies = np.load(folder / "homographies.npy")
    assert homographies.ndim == 3 and np.isfinite(homographies).all()
    return True


def write_plugin(folder: Path, module: str, code: str, dist: str | None = None,
                 entry_points: dict[str, str] | None = None) -> Path:
    """Write a plugin module (and optionally a distribution naming it in entry points) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{module}.py").write_text(textwrap.dedent(code))
    if dist:
        info = folder / f"{dist}-1.0.dist-info"
        info.mkdir(exist_ok=True)
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
        lines = "".join(f"{name} = {target}\n" for name, target in (entry_points or {}).items())
        (info / "entry_points.txt").write_text(f"[photonpano.plugins]\n{lines}")
    return folder


def orb_locator_plugin(name: str) -> str:
    """Source of a plugin module registering ORB's locator config under the locator name ``name``."""
    return f"""
    from typing import Literal

    from photonpano import hookimpl
    from photonpano.plugins.locators.opencv_features import OpenCVOrbConfig


    class Renamed(OpenCVOrbConfig):
        plugin: Literal["{name}"] = "{name}"


    @hookimpl
    def photonpano_register_locators():
        return [Renamed]
"""
