"""The Python API (photonpano.run / photonpano.load), spec paths, and the newcomer's install."""

import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import photonpano
import pytest
from photonpano.errors import PhotonpanoError, SpecError

ROOT = Path(__file__).resolve().parents[1]
TINY = {"source": {"plugin": "simulate", "frames": 2400, "height": 128, "width": 248, "vibration_px": 2.0},
        "group_size": 300, "levels": 2}


@pytest.fixture(scope="module")
def in_memory():
    return photonpano.run(TINY, progress=False)


def test_run_in_memory_returns_arrays_and_writes_nothing(in_memory, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = in_memory
    assert r.homographies.shape == (2400, 3, 3) and r.homographies.dtype == np.float64
    assert r.panorama.ndim == 2 and r.panorama.dtype == np.float32 and np.isfinite(r.panorama).mean() > 0.8
    assert r.out_dir is None and list(tmp_path.iterdir()) == []
    # the motion is right, not just shaped right
    assert r.summary["ground_truth"]["trajectory_rmse_px"] < 0.5
    assert r.spec.levels == 2 and r.summary["versions"]["numpy"] == np.__version__


def test_run_writes_and_load_reads_back(tmp_path, in_memory):
    spec_text = "source: {plugin: simulate, frames: 2400, height: 128, width: 248, vibration_px: 2.0}\n"
    r = photonpano.run(spec_text, out_dir=tmp_path / "run", overrides={"group_size": 300, "levels": 2},
                       progress=False)
    back = photonpano.load(tmp_path / "run")
    np.testing.assert_array_equal(back.homographies, r.homographies)
    np.testing.assert_array_equal(back.panorama, r.panorama)
    assert [row["level"] for row in back.summary["levels"]] == [1, 2]
    assert back.spec.group_size == 300
    # the same photons and settings give the same result in memory and on disk
    np.testing.assert_allclose(r.homographies, in_memory.homographies, atol=1e-9)


def test_run_and_load_errors_are_one_line(tmp_path):
    with pytest.raises(SpecError, match="does not exist"):
        photonpano.run(tmp_path / "missing.yaml", progress=False)
    with pytest.raises(SpecError, match="locator"):
        photonpano.run({"source": "simulate", "locator": "opencv-sfit"}, progress=False)
    with pytest.raises(SpecError, match="mapping"):
        photonpano.run("- a list\n- not a spec\n", progress=False)
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
        f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n" for i in range(8))
    with pytest.raises(SpecError, match="spec text"):  # YAML text gets the spec files' guards
        photonpano.run(bomb, progress=False)
    with pytest.raises(SpecError, match="duplicate|line 2"):
        photonpano.run("levels: 2\nlevels: 3\n", progress=False)
    with pytest.raises(PhotonpanoError, match="no run.json"):
        photonpano.load(tmp_path)
    cube = tmp_path / "capture.npy"
    np.save(cube, np.zeros((4, 8, 8), np.uint8))
    for given in (cube, str(cube)):  # a capture where a spec is expected: pano is named
        with pytest.raises(SpecError, match=r"capture\.npy: a capture \(source npy-cube\), not a YAML pipeline "
                                            r"spec; reconstruct it with `photonpano pano "):
            photonpano.run(given, progress=False)


def test_relative_paths_resolve_against_the_spec_folder_and_are_saved_absolute(tmp_path, host, monkeypatch):
    from photonpano.spec import dump_spec, load_spec

    folder = tmp_path / "project"
    folder.mkdir()
    np.save(folder / "cube.npy", np.zeros((64, 8, 2), np.uint8))
    (folder / "spec.yaml").write_text("source: {plugin: npy-cube, path: cube.npy}\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    spec = load_spec(folder / "spec.yaml", host)
    assert spec.source.path == folder / "cube.npy"
    assert str(folder / "cube.npy") in dump_spec(spec)
    # --set paths are typed on the command line: they resolve against the working directory
    spec = load_spec(folder / "spec.yaml", host, ["source.path=other.npy"])
    assert spec.source.path == elsewhere / "other.npy"


def test_example_runs(capsys):
    runpy.run_path(str(ROOT / "examples" / "api.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "homographies (3000, 3, 3)" in out and "trajectory RMSE" in out and "run.json" in out


def test_numba_cache_stays_out_of_the_package(tmp_path):
    """Compiled kernels are cached per user, never in the installed package (issue 10)."""
    import photonpano.photons as photons
    from photonpano.jit import cache_dir

    env_cache = tmp_path / "cache"
    code = ("import numpy as np; from photonpano.photons import sum_packed_ranges; "
            "print(sum_packed_ranges(np.zeros((4, 2, 1), np.uint8), np.array([0, 4])).sum())")
    import os

    env = {**os.environ, "PHOTONPANO_CACHE_DIR": str(env_cache)}
    env.pop("NUMBA_CACHE_DIR", None)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    package = Path(photons.__file__).parent
    assert not list(package.rglob("*.nbi")) and not list(package.rglob("*.nbc"))
    assert list(env_cache.rglob("*.nbi")), "the kernels were not cached"
    assert cache_dir().name == "numba"


def test_version_and_log_file(tmp_path):
    from photonpano.cli import app
    from typer.testing import CliRunner

    runner = CliRunner()
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"photonpano {photonpano.__version__}"
    log = tmp_path / "run.log"
    result = runner.invoke(app, ["-q", "--log-file", str(log), "demo", "-o", str(tmp_path / "out"), "--frames",
                                 "2400", "--set", "source.height=128", "--set", "source.width=248",
                                 "--set", "group_size=300", "--set", "levels=2"])
    assert result.exit_code == 0, result.output
    text = log.read_text()
    assert "run start" in text and "level 2:" in text and "run finished" in text
    assert "━" not in result.output  # --quiet: no progress bars


def test_keywords_in_path_fields_and_path_lists_are_kept(tmp_path, host):
    """``inpaint_mask: colorspad`` names the bundled mask, not a file next to the spec."""
    from photonpano.spec import resolve_relative_paths

    data = {"source": {"plugin": "npy-cube", "path": "c.npy", "inpaint_mask": "colorspad", "cfa": "cfa.png"},
            "resampler": "midpoint"}
    out = resolve_relative_paths(data, host, tmp_path)
    assert out["source"] == {"plugin": "npy-cube", "path": str(tmp_path / "c.npy"), "inpaint_mask": "colorspad",
                             "cfa": str(tmp_path / "cfa.png")}
    assert data["source"]["path"] == "c.npy"  # the input mapping is not modified
    bins = resolve_relative_paths({"source": {"plugin": "swissspad-bin", "path": ["a.bin", "/abs/b.bin"]}},
                                  host, tmp_path)
    assert bins["source"]["path"] == [str(tmp_path / "a.bin"), "/abs/b.bin"]


def test_every_numba_kernel_caches_outside_the_package():
    """A kernel decorated with ``numba.njit(cache=True)`` writes into site-packages (issue 10)."""
    import re

    offenders = []
    for path in [*ROOT.joinpath("framework").rglob("*.py"), *ROOT.joinpath("plugins").rglob("*.py")]:
        if path.name == "jit.py":
            continue
        text = path.read_text()
        if re.search(r"@(numba\.)?n?jit\([^)]*cache\s*=\s*True", text):
            offenders.append(str(path.relative_to(ROOT)))
    assert not offenders, f"use photonpano.jit.cached_njit in {offenders}"


def test_every_subpackage_is_listed_for_the_wheel():
    """Every subpackage is in pyproject's list.

    One missing installs fine editable, and is absent from the wheel README command 1 installs.
    """
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = set()
    for top, name in (("framework", "photonpano"), ("plugins", "photonpano.plugins")):
        for init in (root / top).rglob("__init__.py"):
            found.add(".".join([name, *init.parent.relative_to(root / top).parts]))
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"
