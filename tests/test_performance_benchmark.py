"""benchmarks/performance.py's timeline: the process's CPU use and the main thread's stage over time."""

import time

import numpy as np
import pytest
from capture_helpers import load_benchmark


def test_the_timeline_shows_one_busy_core_and_the_photonpano_call_it_is_in():
    """Tone-mapping in a loop on the main thread: about one core, and the stage names ``tone_map``."""
    from photonpano.photons import tone_map

    flux = np.random.default_rng(0).random((1500, 1500), dtype=np.float32)
    with load_benchmark("performance").Timeline(step_s=0.05) as timeline:
        end = time.perf_counter() + 1.2
        while time.perf_counter() < end:
            tone_map(flux)
    table = timeline.table(bucket_s=0.25)[:-1]  # the last bucket holds the loop's end
    assert len(table) >= 3
    cores = [float(line.split()[2]) for line in table]  # CPU time counts in 10 ms ticks: 20 % per sample
    assert all(0.3 <= c <= 1.5 for c in cores), table  # one thread busy (less on a loaded machine), the sampler idle
    assert all(line.endswith("tone_map") for line in table), table


def test_repeated_runs_print_their_medians(capsys):
    """``--repeat``: the median of each figure over the runs, every run's wall time, the one RMSE."""
    runs = [{"scene": "city", "path": "zigzag", "frames": 100_000, "wall_s": w, "cpu_s": c, "floor_s": f,
             "ratio": w / f, "peak_rss_mb": m, "rmse_px": 0.051}
            for w, c, f, m in [(15.6, 25.4, 8.0, 612), (13.0, 22.0, 6.0, 611), (14.0, 23.0, 7.0, 640)]]
    load_benchmark("performance").report_medians(runs)
    line = capsys.readouterr().out
    assert "median of 3 runs: wall 14.0 s (15.6, 13.0, 14.0), CPU 23.0 s, floor 7.00 s" in line, line
    assert "pipeline/floor 2.0x" in line and "at most 640 MB" in line and line.count("0.051") == 1, line


def test_a_scene_is_a_named_scene_a_suite_photo_or_any_photo_by_its_path(tmp_path):
    """``--scene``: named scenes and suite stems keep their cache names; a path's name is its stem and content hash."""
    performance = load_benchmark("performance")
    assert performance.scene_key("city") == "city" and performance.scene_key("interior_clock") == "interior_clock"
    photo = tmp_path / "rocket.png"
    photo.write_bytes(b"one")
    assert performance.scene_settings(str(photo)) == {"photo": str(photo.resolve())}
    first = performance.scene_key(str(photo))
    assert first.startswith("rocket-")
    photo.write_bytes(b"two")  # another photo at the same path is another capture
    assert performance.scene_key(str(photo)) != first
    with pytest.raises(SystemExit, match="or a photo's path"):
        performance.scene_settings(str(tmp_path / "missing.png"))
