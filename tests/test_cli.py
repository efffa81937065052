"""The command line: contract of the outputs, one-line errors, no overwriting."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
from photonpano.cli import app
from typer.testing import CliRunner

runner = CliRunner()

TINY = ["--set", "source.height=128", "--set", "source.width=248", "--set", "source.vibration_px=2",
        "--set", "group_size=300", "--set", "levels=2"]


def _cli(*args):
    """Run the installed command in a subprocess (as a user would); return the result."""
    return subprocess.run([sys.executable, "-m", "photonpano.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=600)


def test_demo_writes_the_output_contract(tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(app, ["demo", "-o", str(out), "--frames", "2400", *TINY,
                                 "--set", "outputs.merged_frames=true"])
    assert result.exit_code == 0, result.output
    assert "trajectory RMSE vs ground truth" in result.output and "PSNR" in result.output
    h = np.load(out / "homographies.npy")
    pano = np.load(out / "panorama.npy")
    assert h.shape == (2400, 3, 3) and h.dtype == np.float64
    np.testing.assert_allclose(h[:, 2, 2], 1.0)
    assert pano.dtype == np.float32 and np.isnan(pano).any() and np.isfinite(pano).mean() > 0.8
    png = cv2.imread(str(out / "panorama.png"), cv2.IMREAD_UNCHANGED)  # grey + alpha, read as BGRA
    assert png.dtype == np.uint16 and png.shape == (*pano.shape, 4)
    np.testing.assert_array_equal(png[..., 3], np.where(np.isfinite(pano), 65535, 0))  # unobserved: transparent
    from photonpano.hdr import read_flux_tiff
    tif, valid = read_flux_tiff(out / "panorama.tif")  # the float32 HDR file, with its mask
    assert tif.dtype == np.float32 and np.array_equal(tif, pano, equal_nan=True)
    assert np.array_equal(valid, np.isfinite(pano))
    for level in (1, 2):  # merged frames at every level (level 2 registers against the panorama)
        merged = np.load(out / f"level_{level}" / "merged.npy")
        assert merged.shape[1:] == (128, 248) and np.isfinite(merged).mean() > 0.8
    # every frame's footprint lies on the canvas
    from photonpano.geometry import footprint_bounds
    x0, y0, x1, y1 = footprint_bounds(h, 248, 128)
    assert x0 >= -0.51 and y0 >= -0.51 and x1 <= pano.shape[1] + 0.5 and y1 <= pano.shape[0] + 0.5
    run = json.loads((out / "run.json").read_text())
    assert run["spec"]["levels"] == 2 and len(run["levels"]) == 2
    assert {"merge", "locate", "interpolate"} <= set(run["levels"][0]["timings_s"])
    assert run["levels"][1]["locator_cache"]["misses"] > 0  # feature reuse is reported per level
    assert run["ground_truth"]["trajectory_rmse_px"] < 1.0
    assert "photonpano" in run["plugins"]
    assert (out / "spec.yaml").exists() and (out / "trajectory.png").exists()


def test_refuses_a_non_empty_output_folder(tmp_path):
    (tmp_path / "keep.txt").write_text("user data")
    result = _cli("demo", "-o", tmp_path, "--frames", "1000")
    assert result.returncode == 1
    assert result.stderr.strip().startswith(f"error: output folder {tmp_path} is not empty; choose another, "
                                            "pass --force")
    assert (tmp_path / "keep.txt").read_text() == "user data"


@pytest.mark.parametrize("args, message", [
    (["pano", "missing.npy"], "input missing.npy does not exist"),
    (["validate", "missing.yaml"], "missing.yaml: cannot read spec"),
])
def test_bad_input_is_one_line_without_traceback(tmp_path, args, message):
    result = _cli(*args, *(["-o", tmp_path / "o"] if args[0] == "pano" else []))
    assert result.returncode == 1
    assert message in result.stderr and "Traceback" not in result.stderr + result.stdout
    assert len(result.stderr.strip().splitlines()) == 1


def test_run_given_a_capture_suggests_pano(tmp_path):
    cube = tmp_path / "capture.npy"
    np.save(cube, np.zeros((4, 8, 8), np.uint8))
    result = _cli("run", cube, "-o", tmp_path / "o")
    assert result.returncode == 1 and "Traceback" not in result.stderr + result.stdout
    assert result.stderr.strip() == (f"error: {cube}: a capture (source npy-cube), not a YAML pipeline spec; "
                                     f"reconstruct it with `photonpano pano {cube}`")
    assert not (tmp_path / "o").exists()


def test_wrong_dtype_cube_fails_cleanly_and_is_untouched(tmp_path):
    cube = tmp_path / "cube.npy"
    np.save(cube, np.zeros((10, 8, 8), np.float32))
    before = cube.read_bytes()
    result = _cli("pano", cube, "-o", tmp_path / "out")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert "cube.npy has dtype float32; expected uint8" in result.stderr
    assert cube.read_bytes() == before


def test_pano_reconstructs_a_cube_file(tmp_path, tiny_capture):
    cube = tmp_path / "capture.npy"
    np.save(cube, np.asarray(tiny_capture.cube))
    out = tmp_path / "out"
    result = runner.invoke(app, ["pano", str(cube), "-o", str(out), "--set", "group_size=300", "--set", "levels=2"])
    assert result.exit_code == 0, result.output
    h = np.load(out / "homographies.npy")
    from photonpano.metrics import trajectory_error
    assert trajectory_error(h, tiny_capture.ground_truth, 248, 128).rmse_px < 1.0


def test_validate_plugins_schema(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: {plugin: npy-cube, path: x.npy}\nlocator: {plugin: opencv-sfit}\n")
    result = _cli("validate", spec)
    assert result.returncode == 1 and "did you mean 'opencv-sift'" in result.stderr
    spec.write_text("source: {plugin: npy-cube, path: x.npy}\n")
    assert runner.invoke(app, ["validate", str(spec)]).exit_code == 0
    listing = runner.invoke(app, ["plugins"])
    assert listing.exit_code == 0 and "opencv-sift" in listing.output and "cubic-lk" in listing.output
    schema = json.loads(runner.invoke(app, ["schema"]).output)
    assert "PipelineSpec" == schema["title"]


def test_plugins_table_keeps_install_hints_with_extras(monkeypatch):
    """Rich markup must not swallow ``[kornia]`` in ``pip install 'photonpano[kornia]'``."""
    import types

    import photonpano.cli as cli
    from photonpano.host import PluginInfo

    info = PluginInfo("kornia-sift", "locator", "photonpano.plugins.locators.kornia_sift", "photonpano", "0.1.0",
                      "unavailable: needs torch, kornia: pip install 'photonpano[kornia]'")
    monkeypatch.setattr(cli, "_host", lambda: types.SimpleNamespace(plugin_infos=lambda: [info], collisions=[]))
    result = runner.invoke(app, ["plugins"])
    assert result.exit_code == 0, result.output
    assert "photonpano[kornia]" in result.output
