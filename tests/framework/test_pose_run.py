"""The pose run: level warnings, COLMAP's log routed to Python logging, the atomic run folder."""

from __future__ import annotations

import importlib.util
import json
import logging
import subprocess
import sys

import pytest
from photonpano.pose_run import level_warnings
from typer.testing import CliRunner

needs_pycolmap = pytest.mark.skipif(
    importlib.util.find_spec("pycolmap") is None,
    reason="pycolmap is not installed (pip install 'photonpano[colmap]')",
)

SMALL_ROOM = ["--set", "source.height=128", "--set", "source.width=248", "--set", "source.focal_px=210",
              "--set", "pose_estimator.group_size=500"]


def _row(level, exposures, registered, **extra):
    return {"level": level, "exposures": exposures, "registered": registered, **extra}


def test_levels_that_improve_or_hold_do_not_warn():
    rows = [_row(1, 6, 6, reprojection_error_px=0.75, ate_m=0.0024),
            _row(2, 13, 12, reprojection_error_px=0.06, ate_m=0.0020),
            _row(3, 23, 23, reprojection_error_px=0.12, ate_m=0.0021)]  # 0.06 -> 0.12 px: below the floor
    assert level_warnings(rows) == []
    assert level_warnings(rows[:1]) == []


def test_a_level_worse_than_the_one_before_warns_in_one_line():
    # the case: level 2 registered 6 of 13 exposures, ATE 7.8 mm against 2.1 mm at level 1
    rows = [_row(1, 7, 7, reprojection_error_px=0.7, ate_m=0.0021), _row(2, 13, 6, ate_m=0.0078),
            _row(3, 25, 25, reprojection_error_px=1.6, ate_m=0.0050)]
    found = level_warnings(rows)  # level 3 improved on level 2 (level 2 has no reprojection figure)
    assert len(found) == 1 and "\n" not in found[0]
    assert found[0].startswith("level 2 ended worse than level 1: registered 6 of 13 exposures (46 % against 100 %")
    assert "ATE against the ground truth 7.80 mm against 2.10 mm" in found[0]
    # without ground truth, the run's own figures alone
    own = level_warnings([{k: v for k, v in row.items() if k != "ate_m"} for row in rows])
    assert len(own) == 1 and "registered 6 of 13" in own[0] and "ATE" not in own[0]
    rows = [_row(1, 7, 7, reprojection_error_px=0.7), _row(2, 13, 13, reprojection_error_px=1.2)]
    assert level_warnings(rows) == ["level 2 ended worse than level 1: mean reprojection error 1.20 px against "
                                    "0.70 px"]
    stopped = [_row(1, 7, 7), _row(2, 13, 0, note="too few exposures registered; the previous level's poses "
                                                   "are kept")]
    assert level_warnings(stopped) == ["level 2: too few exposures registered; the previous level's poses are kept"]


@needs_pycolmap
def test_colmap_log_lines_go_to_python_logging_not_to_stderr(capfd, caplog):
    import pycolmap
    from photonpano.plugins.pose._colmap_log import colmap_log

    before = pycolmap.logging.minloglevel
    caplog.set_level(logging.DEBUG, logger="photonpano.colmap")
    with colmap_log():
        pycolmap.bundle_adjustment(pycolmap.Reconstruction(), pycolmap.BundleAdjustmentOptions())
        print("not COLMAP", file=sys.stderr, flush=True)
    err = capfd.readouterr().err
    assert "bundle_adjustment.cc" not in err and "not COLMAP" in err  # other output is passed through
    records = [(r.levelno, r.getMessage()) for r in caplog.records if r.name == "photonpano.colmap"]
    assert (logging.DEBUG, "COLMAP bundle_adjustment.cc:46: === Global bundle adjustment ===") in records
    assert any(level == logging.INFO and "registered frame" in text for level, text in records), records
    assert pycolmap.logging.minloglevel == before


@needs_pycolmap
def test_a_failed_pose_run_leaves_no_folder_behind(tmp_path):
    from photonpano.cli import app

    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["-q", "pose", "simulate3d", "-o", str(out), *SMALL_ROOM,
                                      "--set", "source.frames=3000", "--set", "source.flux=0.0002"])
    assert result.exit_code == 1 and "too dark" in result.output
    assert not out.exists()


@needs_pycolmap
@pytest.mark.slow
def test_pose_run_writes_a_run_folder_and_keeps_colmap_off_stderr(tmp_path):
    out, log = tmp_path / "out", tmp_path / "pose.log"
    command = [sys.executable, "-m", "photonpano.cli", "--log-file", str(log), "pose", "simulate3d", "-o", str(out),
               *SMALL_ROOM, "--set", "source.frames=3000", "--set", "pose_estimator.levels=2"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "COLMAP" not in done.stderr and ".cc:" not in done.stderr, done.stderr  # nothing leaks by default
    assert "COLMAP incremental_pipeline.cc" in log.read_text()  # the log file keeps every line
    summary = json.loads((out / "run.json").read_text())
    assert summary["status"] in ("ok", "degraded") and summary["warnings"] == level_warnings(summary["levels"])
    assert (summary["status"] == "degraded") == bool(summary["warnings"])
    for line in summary["warnings"]:
        assert f"warning: {line}" in done.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] and manifest["files"][-1] == "run.json"
    for name in ("spec.yaml", "poses.npy", "points.ply", "model/cameras.bin", "trajectory.png", "intrinsics.json"):
        assert name in manifest["files"] and name in manifest["sha256"], name
    assert not (out / ".photonpano.lock").exists() and not list(out.rglob(".partial-*"))
