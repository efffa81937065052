"""The same capture gives the same homographies on every executor and worker count.

Before: a Dask run (no block store in its processes) cut its sub-batches on every frame
where serial and threads cut them on blocks of frames, and a panorama or mosaic
template was summed on one canvas per worker: ``dask`` (2 workers) vs ``serial`` differed
by 0.026 px on 4 000 frames, ``threads`` (2) vs ``serial`` by 6.6e-4 px on 20 000.
"""

from __future__ import annotations

import pickle
import time

import numpy as np
import pytest
from photonpano import geometry
from photonpano.budget.grid import BinnedSource, RegistrationGrid
from photonpano.compose import FOLD_RUNS, BilinearCompositor, compose
from photonpano.executor import SerialExecutor, ThreadExecutor
from photonpano.testing import tiny_capture

SPEC = {"source": {"plugin": "simulate", "frames": 4000}, "outputs": {"trajectory_plot": False, "report": False}}
"""The default frame size (254x496: binned 2x2 for registration, like real captures), 4 000 frames."""


def test_the_panorama_does_not_depend_on_the_worker_count():
    capture = tiny_capture(frames=1200, height=64, width=96)
    truth = capture.ground_truth
    panos = {}
    for name, make in {"serial": SerialExecutor, "threads-1": lambda: ThreadExecutor(1),
                       "threads-2": lambda: ThreadExecutor(2), "threads-3": lambda: ThreadExecutor(3)}.items():
        with make() as executor:  # chunks of 2 sub-batches: many chunks, so the runs split them
            panos[name] = compose(capture, truth, BilinearCompositor(), subbatch_px=0.05, chunk_batches=2,
                                  executor=executor).flux
    assert FOLD_RUNS > 1
    for name, flux in panos.items():
        np.testing.assert_array_equal(flux, panos["serial"], err_msg=name)


def test_the_block_grid_does_not_depend_on_the_executor():
    class Elsewhere(SerialExecutor):  # like Dask: tasks run in other processes, no block store here
        in_process = False

    capture = tiny_capture(frames=1600, height=64, width=96)
    grids = {}
    for executor in (SerialExecutor(), Elsewhere()):
        grid = RegistrationGrid(capture, 2)
        grid.count_once(np.arange(0, 1601, 160), 160, executor)
        grids[executor.in_process] = grid
    here, elsewhere = grids[True].source, grids[False].source
    assert here.blocks is not None and elsewhere.blocks is None
    assert here.frame_step == elsewhere.frame_step == 10
    copy = pickle.loads(pickle.dumps(elsewhere))  # a task's copy in a worker process
    assert isinstance(copy, BinnedSource) and copy.frame_step == 10
    edges = np.arange(0, 1601, 40)
    np.testing.assert_array_equal(here.sum_ranges(edges), elsewhere.sum_ranges(edges))
    grids[True].close()


@pytest.mark.slow
def test_serial_threads_and_dask_give_the_same_homographies(tmp_path):
    pytest.importorskip("distributed")
    import photonpano

    results, seconds = {}, {}
    for executor, workers in [("serial", 1), ("threads", 1), ("threads", 2), ("dask", 2)]:
        start = time.perf_counter()
        run = photonpano.run({**SPEC, "executor": executor, "workers": workers}, progress=False)
        results[executor, workers] = run.homographies
        seconds[executor, workers] = time.perf_counter() - start
    corners = geometry.corners(496, 254)
    reference = geometry.apply(results["serial", 1], corners)
    for key, homographies in results.items():  # the worst frame's mean corner distance
        error = np.linalg.norm(geometry.apply(homographies, corners) - reference, axis=-1).mean(axis=-1).max()
        assert error <= 1e-6, (key, error)
    assert sum(seconds.values()) < 180, seconds
