"""benchmarks/performance.py's timeline: the process's CPU use and the main thread's stage over time."""

import time

import numpy as np
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
