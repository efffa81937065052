"""`photonpano compare`: one capture, several locators, a table, a plot and JSON."""

import json

import numpy as np
import pytest
from photonpano.cli import app
from photonpano.compare import markdown_table
from typer.testing import CliRunner

TINY = ["--set", "source.frames=2400", "--set", "source.height=128", "--set", "source.width=248",
        "--set", "source.vibration_px=2", "--set", "group_size=300", "--set", "levels=2"]


@pytest.mark.slow
def test_compare_writes_table_plot_and_json(tmp_path):
    out = tmp_path / "cmp"
    result = CliRunner().invoke(app, ["compare", "simulate", "-o", str(out), "-l",
                                      "opencv-sift:image_scale=1.0,opencv-ecc:pyramid_levels=2,opencv-sfit", *TINY])
    assert result.exit_code == 0, result.output
    runs = json.loads((out / "compare.json").read_text())["runs"]
    # compare registers pairs at every level: opencv-sift at full resolution (its default,
    # half resolution, is tuned to initialise the refinement against the panorama)
    assert [r["locator"] for r in runs] == ["opencv-sift:image_scale=1.0", "opencv-ecc:pyramid_levels=2",
                                            "opencv-sfit"]
    for run in runs[:2]:
        assert run["status"] == "ok" and len(run["levels"]) == 2
        assert run["trajectory_rmse_px"] < 1.0 and run["failed_pairs"] == 0
        assert run["levels"][1]["trajectory_rmse_px"] < run["levels"][0]["trajectory_rmse_px"]
        assert run["locate_s"] > 0 and run["levels"][0]["cache"]["misses"] > 0
        assert np.load(out / run["locator"].replace(":", "_") / "homographies.npy").shape == (2400, 3, 3)
    assert runs[1]["spec"]["pyramid_levels"] == 2
    assert "unknown plugin 'opencv-sfit'" in runs[2]["status"] and "did you mean 'opencv-sift'" in runs[2]["status"]
    table = (out / "compare.md").read_text()
    assert table.count("\n") == 2 + 3 and "| `opencv-ecc:pyramid_levels=2` |" in table
    assert (out / "compare.png").stat().st_size > 10_000
    assert "| `opencv-sift:image_scale=1.0` |" in result.output


def test_compare_refuses_unknown_input_and_empty_list(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["compare", str(tmp_path / "none.npy"), "-o", str(tmp_path / "o"), "-l", "opencv-sift"])
    assert result.exit_code == 1 and "does not exist" in result.output
    result = runner.invoke(app, ["compare", "simulate", "-o", str(tmp_path / "o"), "-l", " , "])
    assert result.exit_code == 1 and "at least one locator" in result.output


def test_markdown_table_reports_failures_and_numbers():
    rows = [{"locator": "a", "status": "ok", "total_s": 12.0, "trajectory_rmse_px": 0.1234,
             "levels": [{"level": 1, "trajectory_rmse_px": 0.5, "failed_pairs": 2, "timings_s": {"locate": 1.5},
                         "cache": {"hits": 3, "misses": 4}}]},
            {"locator": "b", "status": "locator (b): needs kornia: pip install x\nmore", "levels": []}]
    table = markdown_table(rows)
    assert "| `a` | 0.123 | 0.500 | 2 | 1.5 | 12.0 | 3/4 |" in table
    assert "| `b` | – | locator (b): needs kornia: pip install x |" in table


def test_compare_on_a_video_capture_merges_intensities_and_keeps_the_camera_static(tmp_path):
    """A capture of intensity frames gets the `mean` merger, as in `photonpano pano` (the real Photron clip)."""
    pytest.importorskip("pyMRAW")
    from pathlib import Path

    from photonpano.geometry import apply, corners

    clip = Path(__file__).parent / "data" / "highspeed" / "ball_12bit.mraw"
    out = tmp_path / "cmp"
    result = CliRunner().invoke(app, ["compare", str(clip), "-o", str(out), "-l", "opencv-sift",
                                      "--set", "group_size=3", "--set", "levels=2"])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "compare.json").read_text())["runs"][0]["status"] == "ok"
    c = apply(np.load(out / "opencv-sift" / "homographies.npy"), corners(384, 384))
    assert np.abs(c - c[:1]).max() < 1.0


def test_compare_reports_progress_per_locator_and_level():
    """Each locator's levels draw their own bars (the CLI draws them; here a recording observer)."""
    from photonpano import hookimpl
    from photonpano.compare import compare_locators
    from photonpano.host import PluginHost
    from photonpano.progress import reporting

    class Recorder:
        def __init__(self):
            self.done = {}

        @hookimpl
        def photonpano_progress(self, task, total, advance):
            self.done.setdefault(task, [total, 0])[1] += advance

    host, recorder = PluginHost(), Recorder()
    host.register(recorder, name="recorder")
    base = {"source": {"plugin": "simulate", "frames": 1200, "height": 64, "width": 128, "vibration_px": 1},
            "group_size": 300, "levels": 2}
    with reporting(host):
        rows = compare_locators(base, ["opencv-ecc", "opencv-ecc:pyramid_levels=2"], host)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    for row in rows:
        for level in row["levels"]:
            total, done = recorder.done[f"{row['locator']}: level {level['level']}: merge + locate"]
            assert total == done == level["groups"]
    assert len(recorder.done) == 1 + 4  # the simulation, and two levels of each locator
