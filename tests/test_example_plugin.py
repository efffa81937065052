"""The third-party example package examples/photonpano-phasecorr, end to end.

The fixture makes the package discoverable without installing it: a temporary folder
holds its distribution metadata (``photonpano_phasecorr-0.1.0.dist-info`` with the
entry points of its ``pyproject.toml``), and that folder and the package's ``src`` go
first on ``sys.path`` (``PYTHONPATH`` for subprocesses), so they take precedence over an
installed copy and nothing is installed into the environment. Then the package must be
discovered through its entry point, listed by ``photonpano plugins``, selectable in a
spec, pass photonpano's contract tests and run in the pipeline.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).parents[1] / "examples" / "photonpano-phasecorr"


def write_dist_info(site: Path, project: Path) -> Path:
    """Write the ``.dist-info`` folder of the project at ``project`` (name, version, entry points) into ``site``."""
    meta = tomllib.loads((project / "pyproject.toml").read_text())["project"]
    info = site / f"{meta['name'].replace('-', '_')}-{meta['version']}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {meta['name']}\nVersion: {meta['version']}\n")
    groups = "".join(f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n"
                     for group, eps in meta.get("entry-points", {}).items())
    (info / "entry_points.txt").write_text(groups)
    return info


@pytest.fixture(scope="module")
def phasecorr(tmp_path_factory):
    """Make the example package discoverable (sys.path and PYTHONPATH, no install); return its module."""
    site = tmp_path_factory.mktemp("site")
    write_dist_info(site, EXAMPLE)
    paths = [str(site), str(EXAMPLE / "src")]
    saved_path, saved_env = list(sys.path), os.environ.get("PYTHONPATH")
    sys.path[:0] = paths
    os.environ["PYTHONPATH"] = os.pathsep.join(paths + ([saved_env] if saved_env else []))
    importlib.invalidate_caches()
    for name in [m for m in sys.modules if m.split(".")[0] == "photonpano_phasecorr"]:
        del sys.modules[name]
    try:
        yield importlib.import_module("photonpano_phasecorr.plugin")
    finally:
        sys.path[:] = saved_path
        if saved_env is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved_env
        importlib.invalidate_caches()


def test_nothing_is_installed(phasecorr, tmp_path_factory):
    """The distribution found is the fixture's temporary metadata, and the module the source tree."""
    dist = importlib.metadata.distribution("photonpano-phasecorr")
    assert Path(str(dist.locate_file(""))).is_relative_to(tmp_path_factory.getbasetemp())
    assert Path(phasecorr.__file__).is_relative_to(EXAMPLE / "src")


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
