"""``executor: dask`` and ``photonpano batch`` on a distributed cluster bound to 127.0.0.1.

One ``LocalCluster`` of 2 worker processes serves the module. Results on the cluster must
equal the serial ones bit for bit: the merge of photon windows read by the workers from
the file (the source travels as its settings), and whole captures run as Dask tasks.
"""

import functools
import logging
import operator
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from photonpano.cli import app
from photonpano.testing import corner_error_px, tiny_capture
from typer.testing import CliRunner

distributed = pytest.importorskip("distributed")

from photonpano.executor import DaskExecutor, SerialExecutor, process_safe  # noqa: E402

runner = CliRunner()

SMALL = {"frames": 2400, "height": 48, "width": 80, "flux": 0.5}
"""A small simulated capture (a few seconds per run)."""


@pytest.fixture(scope="module")
def scheduler():
    """The address of a 2-worker local cluster (processes, one thread each) on 127.0.0.1."""
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                       dashboard_address=":0", silence_logs=logging.CRITICAL)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def executor(scheduler):
    with DaskExecutor(address=scheduler) as ex:
        yield ex


def test_pure_tasks_run_on_the_workers_in_order(executor):
    assert executor.workers == 2
    assert executor.map(operator.mul, range(20), range(20, 40)) == [a * b for a, b in zip(range(20), range(20, 40))]
    assert executor.map(operator.neg, []) == []
    pids = executor.map(functools.partial(_pid_after, 0.2), range(4))
    assert len(set(pids)) == 2 and os_pid() not in pids  # both worker processes, not this one
    with pytest.raises(ValueError, match="invalid literal"):
        executor.map(int, ["1", "x", "3"])


def _pid_after(seconds, _):
    import os

    time.sleep(seconds)
    return os.getpid()


def os_pid():
    import os

    return os.getpid()


def test_merge_windows_on_the_cluster_equal_serial_bit_for_bit(executor, tmp_path):
    """Photon windows merged by the workers, reading the .npy file themselves, equal serial merges exactly."""
    from photonpano.plugins.sources.npy_cube import NpyCubeConfig
    from photonpano.warping import merge_groups

    cap = tiny_capture(frames=1200)
    np.save(tmp_path / "cube.npy", np.asarray(cap.cube))
    source = NpyCubeConfig(path=tmp_path / "cube.npy").build()
    starts = np.arange(0, 1100, 100)
    windows = [np.arange(s, min(s + 3, len(starts))) for s in range(0, len(starts), 3)]
    task = functools.partial(merge_groups, source, cap.ground_truth)
    args = ([starts[w] for w in windows], [starts[w] + 100 for w in windows], [starts[w] + 50 for w in windows],
            [0.5] * len(windows))
    assert process_safe(task)
    on_cluster, serial = executor.map(task, *args), SerialExecutor().map(task, *args)
    assert len(on_cluster) == len(windows)
    for window_a, window_b in zip(on_cluster, serial):
        for (sums_a, frames_a), (sums_b, frames_b) in zip(window_a, window_b):
            np.testing.assert_array_equal(sums_a, sums_b)
            np.testing.assert_array_equal(frames_a, frames_b)
    assert sum(float(s.sum()) for w in on_cluster for s, _ in w) > 1000  # photons were merged


def test_tasks_that_change_their_callers_variables_run_locally_with_a_warning(executor, caplog):
    out = {}

    def fill(i):
        out[i] = i * i

    assert not process_safe(fill) and not process_safe(functools.partial(fill))
    with caplog.at_level(logging.WARNING, logger="photonpano"):
        executor.map(fill, range(5))
        executor.map(fill, range(5, 8))
    assert out == {i: i * i for i in range(8)}  # the changes were not lost in another process
    warned = [r.getMessage() for r in caplog.records if "fill" in r.getMessage()]
    assert len(warned) == 1 and "runs in this process" in warned[0]


def _write_specs(folder, n):
    specs = []
    for i, path in zip(range(n), ("pan", "zigzag", "shake")):
        spec = folder / f"cap{i}.yaml"
        fields = ", ".join(f"{k}: {v}" for k, v in {**SMALL, "seed": i, "path": path}.items())
        spec.write_text(f"source: {{plugin: simulate, {fields}}}\noutputs: {{trajectory_plot: false}}\n")
        specs.append(spec)
    return specs


def _serial(spec):
    import photonpano

    return photonpano.run(spec, overrides=["executor=serial"], progress=False).homographies


def test_batch_on_the_cluster_matches_serial_runs_and_reports_failures(scheduler, tmp_path):
    specs = _write_specs(tmp_path, 2)
    out = runner.invoke(app, ["batch", *map(str, specs), str(tmp_path / "missing.npy"), "simulate",
                              "-o", str(tmp_path / "out"), "--set", "executor=dask", "--set",
                              f"dask_address={scheduler}", "--set", "source.frames=2400",
                              "--set", "source.height=48", "--set", "source.width=80"])
    assert out.exit_code == 1, out.output  # one capture failed
    assert "capture" in out.output and "missing.npy failed: input" in out.output
    assert len(re.findall(r"│ ok ", out.output)) == 3  # summary table rows
    for spec in specs:
        folder = tmp_path / "out" / spec.stem
        got = np.load(folder / "homographies.npy")
        want = _serial(spec)
        assert corner_error_px(got, want, SMALL["width"], SMALL["height"]) <= 1e-6
        np.testing.assert_array_equal(got, want)  # the same serial pipeline ran on a worker
    assert (tmp_path / "out" / "simulate" / "run.json").is_file()
    assert not (tmp_path / "out" / "missing").exists()


@pytest.mark.slow
def test_batch_on_a_process_pool_and_repeated_stems(tmp_path):
    spec = _write_specs(tmp_path, 1)[0]
    (tmp_path / "other").mkdir()
    shutil.copy(spec, tmp_path / "other" / spec.name)
    out = runner.invoke(app, ["batch", str(spec), str(tmp_path / "other" / spec.name), "-o", str(tmp_path / "out"),
                              "--set", "workers=2"])
    assert out.exit_code == 0, out.output
    first, second = (np.load(tmp_path / "out" / name / "homographies.npy") for name in ("cap0", "cap0-2"))
    np.testing.assert_array_equal(first, _serial(spec))
    np.testing.assert_array_equal(first, second)
    again = runner.invoke(app, ["batch", str(spec), "-o", str(tmp_path / "out"), "--set", "workers=1"])
    assert again.exit_code == 1 and "not empty" in again.output  # never overwrites without --force


@pytest.mark.parametrize("address, expected", [
    ("tcp://127.0.0.1:1", r"dask_address: no Dask scheduler answers at 'tcp://127.0.0.1:1'"),
    ("127.0.0.1:8786", r"dask_address: String should match pattern"),
])
def test_bad_dask_address_is_one_line_naming_the_field(tmp_path, address, expected):
    out = runner.invoke(app, ["batch", "simulate", "-o", str(tmp_path / "out"), "--set", "executor=dask",
                              "--set", f"dask_address={address}"])
    assert out.exit_code == 1
    lines = [line for line in out.output.splitlines() if line.strip()]
    assert len(lines) == 1 and re.search(expected, lines[0]), out.output
    assert "Traceback" not in out.output


@pytest.mark.slow
def test_pipeline_with_executor_dask_matches_serial(tmp_path):
    """A whole run with ``executor: dask`` gives the serial homographies (within 1e-6 px)."""
    import photonpano

    spec = _write_specs(tmp_path, 1)[0]
    got = photonpano.run(spec, overrides=["executor=dask", "workers=2"], progress=False).homographies
    assert corner_error_px(got, _serial(spec), SMALL["width"], SMALL["height"]) <= 1e-6


@pytest.mark.slow
def test_separately_started_scheduler_and_workers(tmp_path):
    """``dask scheduler`` + 2 ``dask worker`` processes on loopback run a batch and merge tasks."""
    dask = str(Path(sys.executable).parent / "dask")
    file = tmp_path / "scheduler.json"
    common = ["--no-dashboard"]
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--scheduler-file",
                               str(file), *common], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", str(file), "--nthreads", "1",
                                           "--host", "127.0.0.1", *common],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        deadline = time.time() + 60
        while not file.exists() and time.time() < deadline:
            time.sleep(0.2)
        import json

        address = json.loads(file.read_text())["address"]
        with distributed.Client(address, timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
        spec = _write_specs(tmp_path, 1)[0]
        out = runner.invoke(app, ["batch", str(spec), "simulate", "-o", str(tmp_path / "out"), "--set",
                                  "executor=dask", "--set", f"dask_address={address}", "--set",
                                  "source.frames=2400", "--set", "source.height=48", "--set", "source.width=80"])
        assert out.exit_code == 0, out.output
        np.testing.assert_array_equal(np.load(tmp_path / "out" / "cap0" / "homographies.npy"), _serial(spec))
        with DaskExecutor(address=address) as ex:
            assert ex.workers == 2
            assert ex.map(operator.add, [1, 2, 3], [10, 20, 30]) == [11, 22, 33]
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            proc.wait(timeout=30)


def _hang_in_a_merge(_):
    """A task whose plugin call never returns (a merger waiting on a licence server)."""
    from photonpano import watchdog

    class Merger:
        class config:  # noqa: N801 - mimics a plugin's validated config
            plugin = "my-merger"

    with watchdog.watched("merger", Merger(), "merge"):
        while True:
            time.sleep(0.05)


def _two_calls(seconds):
    """A task of two plugin calls of ``seconds`` each; returns the worker's process id."""
    import os

    from photonpano import watchdog

    for _ in range(2):
        with watchdog.watched("locator", object(), "register_to_template"):
            time.sleep(seconds)
    return os.getpid()


def test_a_plugin_call_hung_on_a_worker_ends_a_guarded_map_naming_it(monkeypatch):
    """The calling process asks the workers what they run: a call past the limit is one line, within the bound."""
    import os

    from photonpano import watchdog

    monkeypatch.setenv(watchdog.ENV, "1")
    with DaskExecutor(workers=1) as executor:  # its own cluster: the hung worker thread is not the module's
        with watchdog.guarding():  # each call under the limit, the task (1.4 s) over it: not a hang
            assert executor.map(_two_calls, [0.7]) != [os.getpid()]
        start = time.perf_counter()
        with pytest.raises(watchdog.PluginHung) as info:
            with watchdog.guarding():
                executor.map(_hang_in_a_merge, [0])
        took = time.perf_counter() - start
        message = str(info.value)
        assert message.startswith("merger (my-merger) in merge on a Dask worker did not return within 1 s")
        assert watchdog.ENV in message and "\n" not in message
        assert 1 <= took < 10, took
