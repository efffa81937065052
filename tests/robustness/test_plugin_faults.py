"""Plugins that misbehave: name collisions, exits at import, exceptions at run time; Ctrl-C."""

from __future__ import annotations

import importlib
import os
import sys
import threading
import time

import pytest
from photonpano import cli
from photonpano.host import PluginHost
from robust import TINY, assert_one_line_error, invoke, orb_locator_plugin, run_subprocess, write_plugin

BOOM_LOCATOR = """
    from typing import Literal

    from photonpano import hookimpl
    from photonpano.stages import Locator, LocatorConfig


    class BoomLocatorConfig(LocatorConfig):
        plugin: Literal["boom-locator"] = "boom-locator"

        def build(self):
            return BoomLocator()


    class BoomLocator(Locator):
        def _register_pairs(self, merged, pairs, initial, context):
            raise RuntimeError("boom in register_pairs " + "x" * 5000)


    @hookimpl
    def photonpano_register_locators():
        return [BoomLocatorConfig]
"""

BASE_BOOM_LOCATOR = BOOM_LOCATOR.replace("boom-locator", "base-boom").replace(
    'raise RuntimeError("boom in register_pairs " + "x" * 5000)', 'raise Boom("not an Exception")').replace(
    "class BoomLocator(Locator):", "class Boom(BaseException):\n        pass\n\n\n    class BoomLocator(Locator):")
"""A locator raising a BaseException subclass that is not an Exception."""

BOOM_OBSERVER = """
    from photonpano import hookimpl


    @hookimpl
    def photonpano_level_finished(level):
        raise ZeroDivisionError("observer bug")
"""

BOOM_INPUT = """
    from photonpano import hookimpl


    @hookimpl
    def photonpano_source_for_input(path):
        raise KeyError(str(path))
"""

EXITS = """
    import sys

    sys.exit(3)
"""

SHADOW_SIFT = orb_locator_plugin("opencv-sift")


def _host_with(monkeypatch, tmp_path, **modules):
    """A host with the built-ins and ``name=code`` plugin modules registered in code."""
    folder = tmp_path / "plugins"
    for name, code in modules.items():
        write_plugin(folder, name, code)
    monkeypatch.syspath_prepend(str(folder))
    host = PluginHost()
    for name in modules:
        sys.modules.pop(name, None)
        host.register(importlib.import_module(name), name=name)
    monkeypatch.setattr(cli, "_host", lambda: host)
    return host


def test_a_locator_bug_names_the_locator(monkeypatch, tmp_path):
    _host_with(monkeypatch, tmp_path, boom_locator=BOOM_LOCATOR)
    result = invoke("demo", "-o", tmp_path / "out", *TINY, "--set", "locator=boom-locator")
    line = assert_one_line_error(result, "locator (boom-locator)", "RuntimeError", "boom in register_pairs",
                                 "traceback in")
    log = line.split("traceback in ")[1].split(";")[0]
    assert "register_pairs" in open(log).read()
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("executor", ["serial", "threads"])
def test_a_locator_raising_a_base_exception_names_the_locator(monkeypatch, tmp_path, executor):
    _host_with(monkeypatch, tmp_path, base_boom=BASE_BOOM_LOCATOR)
    start = time.perf_counter()
    result = invoke("demo", "-o", tmp_path / "out", *TINY, "--set", "locator=base-boom", "--set",
                    f"executor={executor}", "--set", "workers=2")
    assert_one_line_error(result, "locator (base-boom)", "Boom: not an Exception")
    assert time.perf_counter() - start < 10
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_base_exception_on_a_dask_worker_names_the_locator(tmp_path):
    """Raised on a worker, Dask's client re-raised it in its event loop and the run waited forever."""
    pytest.importorskip("distributed")
    env = _dist_env(tmp_path, "base_boom", BASE_BOOM_LOCATOR, {"base-boom": "base_boom"})
    start = time.perf_counter()
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "mosaic.locator=base-boom", "--set",
                            "executor=dask", "--set", "workers=2", env=env, timeout=120)
    assert time.perf_counter() - start < 60 and result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "locator (base-boom)" in errors[0] and "Boom: not an Exception" in errors[0]
    assert not (tmp_path / "out").exists()


IN_KERNEL = 'raise SystemError("CPUDispatcher(<function k>) returned a result with an exception set") from ' \
    "KeyboardInterrupt()"  # Ctrl-C while a numba kernel ran


@pytest.mark.parametrize("raised,exit_code", [("raise KeyboardInterrupt(7)", 130), ("raise SystemExit(7)", 7),
                                              (IN_KERNEL, 130)])
def test_interrupts_from_a_locator_still_propagate(monkeypatch, tmp_path, raised, exit_code):
    """Ctrl-C (exit 130), also inside a compiled kernel, and sys.exit(7) are not reported as the plugin's bug."""
    code = BOOM_LOCATOR.replace('raise RuntimeError("boom in register_pairs " + "x" * 5000)', raised)
    _host_with(monkeypatch, tmp_path, boom_locator=code)
    result = invoke("demo", "-o", tmp_path / "out", *TINY, "--set", "locator=boom-locator")
    assert result.exit_code == exit_code and "plugin code raised" not in result.stderr


def test_an_observer_bug_names_the_plugin_and_hook(monkeypatch, tmp_path):
    _host_with(monkeypatch, tmp_path, boom_observer=BOOM_OBSERVER)
    assert_one_line_error(invoke("demo", "-o", tmp_path / "out", *TINY), "plugin 'boom_observer'",
                          "photonpano_level_finished", "ZeroDivisionError: observer bug")
    assert not (tmp_path / "out").exists()


def test_a_source_for_input_bug_names_the_plugin(monkeypatch, tmp_path, small_cube):
    _host_with(monkeypatch, tmp_path, boom_input=BOOM_INPUT)
    assert_one_line_error(invoke("pano", small_cube, "-o", tmp_path / "out"), "plugin 'boom_input'",
                          "photonpano_source_for_input", "KeyError")


def test_debug_shows_the_traceback(monkeypatch, tmp_path):
    _host_with(monkeypatch, tmp_path, boom_observer=BOOM_OBSERVER)
    result = invoke("--debug", "demo", "-o", tmp_path / "out", *TINY)
    assert result.exit_code != 0 and isinstance(result.exception, ZeroDivisionError)


def test_a_key_registered_twice_keeps_the_built_in(monkeypatch, tmp_path):
    host = _host_with(monkeypatch, tmp_path, shadow=SHADOW_SIFT)
    assert host.registry("locator")["opencv-sift"].__module__ == "photonpano.plugins.locators.opencv_sift"
    assert any("'opencv-sift'" in note and "shadow" in note for note in host.collisions)
    rows = {row.key: row.status for row in host.plugin_infos()}
    assert "already registered" in rows["shadow"]


def _dist_env(tmp_path, module, code, entry_points):
    folder = write_plugin(tmp_path / "site", module, code, dist="evil-plugins", entry_points=entry_points)
    return {"PYTHONPATH": os.pathsep.join([str(folder), os.environ.get("PYTHONPATH", "")])}


def test_an_entry_point_named_like_a_built_in_does_not_replace_it(tmp_path):
    env = _dist_env(tmp_path, "shadow", SHADOW_SIFT, {"opencv-sift": "shadow", "evil-sift": "shadow"})
    listing = run_subprocess("plugins", env=env)
    assert listing.returncode == 0, listing.stderr
    row = next(line for line in listing.stdout.splitlines() if "opencv-sift (evil-plugins)" in line)
    assert "collision: entry point 'opencv-sift' of evil-plugins (shadow)" in row  # the table may wrap the rest
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: simulate\n")
    result = run_subprocess("validate", spec, env=env)
    assert result.returncode == 0
    assert "plugin: opencv-sift" in result.stdout and "ratio" in result.stdout  # the built-in SIFT's fields


def test_the_collision_is_reported_at_run_time(tmp_path):
    env = _dist_env(tmp_path, "shadow", SHADOW_SIFT, {"evil-sift": "shadow"})
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "levels=1", env=env)
    assert result.returncode == 0, result.stderr
    assert "warning:" in result.stderr and "'opencv-sift'" in result.stderr and "ignored" in result.stderr


def test_a_plugin_calling_sys_exit_at_import_is_contained(tmp_path):
    env = _dist_env(tmp_path, "exits", EXITS, {"exits": "exits"})
    listing = run_subprocess("plugins", env=env)
    assert listing.returncode == 0, listing.stderr
    assert "SystemExit" in listing.stdout and "opencv-sift" in listing.stdout
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: simulate\n")
    assert run_subprocess("validate", spec, env=env).returncode == 0


def test_ctrl_c_stops_the_thread_pool_within_a_second():
    """Interrupted, the pool cancels queued tasks and running ones stop at their next check."""
    import signal

    from photonpano.executor import ThreadExecutor

    def task(i, executor):
        for _ in range(200):  # 10 s of work in 50 ms chunks
            executor.raise_if_cancelled()
            time.sleep(0.05)

    executor = ThreadExecutor(2)
    # Python's Ctrl-C handler, also when pytest runs as a background job (which starts with SIGINT ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()  # as Ctrl-C does
        start = time.perf_counter()
        with pytest.raises(KeyboardInterrupt):
            with executor:
                executor.map(task, range(8), [executor] * 8)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert time.perf_counter() - start < 1.3
