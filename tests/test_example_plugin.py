"""The third-party example package examples/photonpano-phasecorr, end to end.

The session fixture installs it (editable, no dependencies, no network) if it is not
installed yet; then the package must be discovered through its entry point, listed by
``photonpano plugins``, selectable in a spec, pass photonpano's contract tests and run
in the pipeline.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).parents[1] / "examples" / "photonpano-phasecorr"


@pytest.fixture(scope="session")
def phasecorr():
    """Install the example package into this environment once; return its module."""
    try:
        importlib.metadata.distribution("photonpano-phasecorr")
    except importlib.metadata.PackageNotFoundError:
        cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "-e", str(EXAMPLE)]
        done = subprocess.run([*cmd[:5], "--no-build-isolation", *cmd[5:]], capture_output=True, text=True)
        if done.returncode != 0:  # e.g. no local setuptools: let pip fetch the build backend
            subprocess.run(cmd, check=True, capture_output=True, text=True)
        importlib.invalidate_caches()
    # an editable install is importable in new interpreters; this one may predate its .pth
    try:
        return importlib.import_module("photonpano_phasecorr.plugin")
    except ImportError:
        sys.path.insert(0, str(EXAMPLE / "src"))
        return importlib.import_module("photonpano_phasecorr.plugin")


def test_discovered_through_its_entry_point(phasecorr):
    from photonpano.host import GROUP, PluginHost

    eps = {ep.name: ep for ep in importlib.metadata.entry_points(group=GROUP)}
    assert eps["phasecorr"].value == "photonpano_phasecorr.plugin"
    assert eps["phasecorr"].dist.name == "photonpano-phasecorr"
    host = PluginHost()
    assert host.registry("locator")["phasecorr"].__name__ == "PhaseCorrConfig"
    info = next(i for i in host.plugin_infos() if i.key == "phasecorr")
    assert (info.stage, info.distribution, info.version, info.status) == ("locator", "photonpano-phasecorr",
                                                                          "0.1.0", "ok")


def test_listed_by_the_plugins_command(phasecorr):
    out = subprocess.run([sys.executable, "-m", "photonpano.cli", "plugins"], capture_output=True, text=True,
                         check=True).stdout
    row = next(line for line in out.splitlines() if "phasecorr" in line)
    assert "locator" in row and "photonpano-phasecorr" in row and "ok" in row


def test_selectable_in_a_spec_file(phasecorr, tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: {plugin: simulate, frames: 1000}\nlocator: {plugin: phasecorr, min_response: 0.1}\n")
    done = subprocess.run([sys.executable, "-m", "photonpano.cli", "validate", str(spec)], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    assert "plugin: phasecorr" in done.stdout and "min_response: 0.1" in done.stdout
    spec.write_text("source: {plugin: simulate}\nlocator: {plugin: phasecorr, min_response: 2}\n")
    done = subprocess.run([sys.executable, "-m", "photonpano.cli", "validate", str(spec)], capture_output=True,
                          text=True)
    assert done.returncode == 1 and "line 2: locator (phasecorr).min_response" in done.stderr


def test_passes_the_contract_tests(phasecorr):
    """The package's own test suite: photonpano.testing.LocatorContract on its locator."""
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(EXAMPLE / "tests")],
                          capture_output=True, text=True, cwd=EXAMPLE)
    assert done.returncode == 0, done.stdout[-3000:]
    assert " passed" in done.stdout and "failed" not in done.stdout


def test_runs_in_the_pipeline(phasecorr, tiny_capture):
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.spec import validate_spec

    spec = validate_spec({"source": {"plugin": "simulate", "frames": 2400}, "locator": "phasecorr",
                          "levels": 2, "group_size": 300}, PluginHost())
    homographies, stats, _, _ = reconstruct(spec, tiny_capture)
    assert stats[-1]["failed_pairs"] == 0
    assert stats[-1]["trajectory_rmse_px"] < 1.0
    assert homographies.shape == (2400, 3, 3) and np.isfinite(homographies).all()
