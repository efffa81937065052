"""A plugin stage call that hangs at run time ends the run within the limit, one line naming plugin and method."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest
from photonpano import watchdog
from robust import COMPILED_AT_FIRST_CALL, TINY, assert_one_line_error, run_subprocess, write_plugin

HANGING_LOCATOR = """
    import time
    from typing import Literal

    from photonpano import hookimpl
    from photonpano.locator import Locator
    from photonpano.plugins.locators.opencv_features import OpenCVOrbConfig


    class Stuck(Locator):
        def __init__(self, config):
            self.config = config

        def _register_pairs(self, merged, pairs, initial, context):
            while True:  # e.g. waiting on a licence server
                try:
                    time.sleep(0.1)
                except KeyboardInterrupt:  # a bare `except:` in plugin code swallows the interrupt
                    if self.config.how == "sleep":
                        raise

        def _register_to_template(self, views, frames, initial, context):
            while True:  # the mosaic levels' call (on a Dask worker in test_a_hang_on_a_dask_worker...)
                time.sleep(0.1)


    class StuckConfig(OpenCVOrbConfig):
        plugin: Literal["stuck-locator"] = "stuck-locator"
        how: str = "sleep"

        def build(self):
            return Stuck(self)


    @hookimpl
    def photonpano_register_locators():
        return [StuckConfig]
"""


def _env(tmp_path, limit_s: float = 2.0) -> dict[str, str]:
    folder = write_plugin(tmp_path / "site", "stuck", HANGING_LOCATOR, dist="stuck-locator",
                          entry_points={"stuck-locator": "stuck"})
    return {"PYTHONPATH": os.pathsep.join([str(folder), os.environ.get("PYTHONPATH", "")]),
            watchdog.ENV: str(limit_s)}


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["serial", "threads"])
def test_a_hanging_locator_ends_the_run_naming_it(tmp_path, executor):
    """Sleeping forever in register_pairs, on the main thread or a worker thread: one line after the 2 s limit."""
    start = time.perf_counter()
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "locator=stuck-locator",
                            "--set", f"executor={executor}", "--set", "workers=2", env=_env(tmp_path), timeout=120)
    took = time.perf_counter() - start
    assert_one_line_error(result, "locator (stuck-locator) in register_pairs", "did not return within 2 s",
                          watchdog.ENV)
    assert took < 60  # start-up, the simulation and 2 s; the process does not wait for the stuck thread
    assert not (tmp_path / "out" / "run.json").exists()


@pytest.mark.slow
def test_a_run_started_with_sigint_ignored_still_ends_a_hanging_locator(tmp_path):
    """As a background job of a non-interactive shell (``photonpano demo ... &``): SIGINT ignored from the start."""
    start = time.perf_counter()
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "locator=stuck-locator",
                            env=_env(tmp_path), timeout=120, sigint=signal.SIG_IGN)
    took = time.perf_counter() - start
    assert_one_line_error(result, "locator (stuck-locator) in register_pairs", "did not return within 2 s",
                          watchdog.ENV)
    assert took < 60  # the interrupt came in time, not the grace period's hard exit
    assert not (tmp_path / "out" / "run.json").exists()


@pytest.mark.slow
def test_a_hang_on_a_dask_worker_ends_the_run_naming_it_and_keeps_the_checkpoint(tmp_path):
    """The mosaic level's locator hangs in a task on a Dask worker: one line, level 1's checkpoint kept.

    The limit is 6 s, not 2: the worker's first merge imports numba and loads the compiled
    kernels, which took over 2 s with the tests running in two processes (the merger was
    named instead of the locator).
    """
    pytest.importorskip("distributed")
    from photonpano import outputs

    start = time.perf_counter()
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "mosaic.locator=stuck-locator",
                            "--set", "executor=dask", "--set", "workers=1", env=_env(tmp_path, limit_s=6.0),
                            timeout=180)
    took = time.perf_counter() - start
    notes = "executor dask: FeatureLocator._matched"  # level 1's feature locator: its closures run here (logged)
    result.stderr = "\n".join(line for line in result.stderr.splitlines() if not line.startswith(notes))
    assert_one_line_error(result, "locator (stuck-locator) in register_to_template on a Dask worker",
                          "did not return within 6 s", watchdog.ENV)
    assert took < 90  # start-up, the cluster, level 1 and 6 s (+ the check's period)
    assert not (tmp_path / "out" / "run.json").exists()
    assert [p.name for p in (tmp_path / "out" / outputs.CHECKPOINTS).iterdir()] == ["level_1.npz"]


@pytest.mark.slow
def test_a_locator_swallowing_the_interrupt_ends_the_command_after_the_grace_period(tmp_path):
    """The main thread never takes the interrupt: the command prints the line and exits all the same."""
    start = time.perf_counter()
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "locator=stuck-locator",
                            "--set", "locator.how=swallow", env=_env(tmp_path), timeout=120)
    assert_one_line_error(result, "locator (stuck-locator) in register_pairs", "did not return within 2 s")
    assert time.perf_counter() - start < 60 + watchdog.GRACE_S


class _Plugin:
    class config:  # noqa: N801 - mimics a plugin's validated config
        plugin = "my-merger"


def test_a_watched_call_past_the_limit_raises_plugin_hung(monkeypatch):
    monkeypatch.delenv(watchdog.ENV, raising=False)
    with watchdog.guarding(), watchdog.watched("merger", _Plugin(), "merge"):  # the watchdog runs, at 600 s
        pass
    monkeypatch.setenv(watchdog.ENV, "0.3")  # the message gives the limit of the call, not of the watchdog's start
    start = time.perf_counter()
    with pytest.raises(watchdog.PluginHung) as info:
        with watchdog.guarding(), watchdog.watched("merger", _Plugin(), "merge"):
            while time.perf_counter() - start < 30:
                time.sleep(0.01)
    took = time.perf_counter() - start
    assert 0.3 <= took < 5, took
    message = str(info.value)
    assert message.startswith("merger (my-merger) in merge did not return within 0.3 s") and "\n" not in message
    assert watchdog.longest["merger.merge"] >= 0.3
    with watchdog.guarding(), watchdog.watched("merger", _Plugin(), "merge"):  # a later run starts clean
        time.sleep(0.05)


def test_calls_within_the_limit_or_unguarded_or_switched_off_are_left_alone(monkeypatch):
    monkeypatch.setenv(watchdog.ENV, "0.2")
    with watchdog.guarding(), watchdog.watched("locator", _Plugin(), "register_pairs"):
        time.sleep(0.05)
    with watchdog.watched("locator", _Plugin(), "register_pairs"):  # no run around it: not watched
        time.sleep(0.5)
    monkeypatch.setenv(watchdog.ENV, "off")
    assert watchdog.limit_s() is None
    with watchdog.guarding(), watchdog.watched("locator", _Plugin(), "register_pairs"):
        time.sleep(0.5)
    for text, expected in (("", watchdog.HOOK_TIMEOUT_S), ("abc", watchdog.HOOK_TIMEOUT_S), ("0", None),
                           ("-3", None), ("45", 45.0)):
        monkeypatch.setenv(watchdog.ENV, text)
        assert watchdog.limit_s() == expected, text


@pytest.mark.slow
def test_compare_records_a_hanging_locator_and_runs_the_next(tmp_path):
    """The hung locator's row says so; the comparison goes on with the next locator and completes."""
    import json

    out = tmp_path / "cmp"
    result = run_subprocess("compare", "simulate", "-o", out, "-l", "stuck-locator,opencv-orb", *TINY,
                            "--set", "levels=1", env=_env(tmp_path), timeout=120)
    assert result.returncode == 0, result.stderr
    runs = json.loads((out / "compare.json").read_text())["runs"]
    assert runs[0]["status"].startswith("locator (stuck-locator) in register_pairs did not return within 2 s")
    assert runs[1]["status"] == "ok"


@pytest.fixture
def sigint_ignored():
    """This process with SIGINT ignored, as a background job of a non-interactive shell starts."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    yield
    signal.signal(signal.SIGINT, previous)


def test_the_watchdog_does_not_depend_on_sigint_and_wakes_a_blocking_wait(monkeypatch, sigint_ignored):
    """A main thread blocked on an event that nobody sets (as on a stuck worker's future) is interrupted."""
    monkeypatch.setenv(watchdog.ENV, "0.3")
    before = signal.getsignal(watchdog.SIGNAL)
    start = time.perf_counter()
    with pytest.raises(watchdog.PluginHung, match=r"^merger \(my-merger\) in merge did not return within 0.3 s"):
        with watchdog.guarding(), watchdog.watched("merger", _Plugin(), "merge"):
            threading.Event().wait()  # no timeout: only a signal wakes it
    assert 0.3 <= time.perf_counter() - start < 5
    assert signal.getsignal(watchdog.SIGNAL) is before  # the handler is put back once the interrupt was taken
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_a_foreign_signal_goes_to_the_previous_handler(monkeypatch):
    """SIGUSR2 from elsewhere during a run reaches the handler installed before it; the run goes on."""
    monkeypatch.setenv(watchdog.ENV, "5")
    seen = []
    previous = signal.signal(watchdog.SIGNAL, lambda signum, frame: seen.append(signum))
    try:
        with watchdog.guarding(), watchdog.watched("merger", _Plugin(), "merge"):
            assert signal.getsignal(watchdog.SIGNAL) is not previous  # the watchdog's own, while guarded
            os.kill(os.getpid(), watchdog.SIGNAL)
            time.sleep(0.2)  # the handler runs in the main thread at its next bytecode
        assert seen == [watchdog.SIGNAL]
    finally:
        signal.signal(watchdog.SIGNAL, previous)


_HANG_WHILE_NUMBA_COMPILES = """
import os, sys, time, traceback
import numba
import numpy as np
from photonpano import watchdog

os.environ[watchdog.ENV] = "0.05"  # passed while the kernel compiles (~0.3 s)


class Plugin:
    class config:
        plugin = "my-merger"

""" + COMPILED_AT_FIRST_CALL + """
try:
    with watchdog.guarding(), watchdog.watched("merger", Plugin(), "merge"):
        kernel(np.ones(4))
        sys.stdout.write("compiled\\n")  # one write: print() writes its text and its newline apart
        time.sleep(5)
except watchdog.PluginHung as hung:
    interrupt = hung.__context__
    inside = any(frame.f_code.co_filename.startswith(os.path.dirname(numba.__file__))
                 for frame, _ in traceback.walk_tb(interrupt.__traceback__))
    print("hung inside numba" if inside else "hung", flush=True)
    sys.exit(1)
"""


def test_a_hang_reported_while_numba_compiles_waits_for_the_compile(tmp_path):
    """The watchdog's interrupt is held back inside numba and llvmlite, as Ctrl-C is (``faults``).

    Raised there it would be lost (the run goes on past its limit) or leave LLVM's state
    half-built (a segmentation fault on the way out).
    """
    import subprocess
    import sys

    script = tmp_path / "compile.py"
    script.write_text(_HANG_WHILE_NUMBA_COMPILES)
    start = time.perf_counter()
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60,
                            env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    assert result.returncode == 1, result.stderr
    # the interrupt may come before or after "compiled" is written, never inside numba
    assert result.stdout.split()[-1:] == ["hung"] and "inside" not in result.stdout, result.stdout
    assert "Exception ignored" not in result.stderr
    assert time.perf_counter() - start < 5  # the interrupt came right after the compile, not after the sleep
