"""Killed at any moment, a folder has no run.json or a complete run; --resume equals an uninterrupted run."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from photonpano import outputs
from robust import COMPILED_AT_FIRST_CALL, SMALL_SPEC, assert_sound_folder, run_subprocess, sigint_as


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The spec, the homographies of an uninterrupted run of it and its wall time in seconds."""
    folder = tmp_path_factory.mktemp("reference")
    spec = folder / "spec.yaml"
    spec.write_text(SMALL_SPEC)
    start = time.perf_counter()
    result = run_subprocess("run", spec, "-o", folder / "out")
    assert result.returncode == 0, result.stderr
    return spec, np.load(folder / "out" / "homographies.npy"), time.perf_counter() - start


def _start(spec, out, stderr=subprocess.DEVNULL):
    return subprocess.Popen([sys.executable, "-m", "photonpano.cli", "run", str(spec), "-o", str(out)],
                            stdout=subprocess.DEVNULL, stderr=stderr,
                            preexec_fn=sigint_as(signal.SIG_DFL))  # Ctrl-C works even if pytest ignores SIGINT


@pytest.mark.slow
def test_kill_9_at_random_moments_then_resume(reference, tmp_path):
    spec, expected, duration = reference
    rng = random.Random(13)
    forced = False
    for k in range(8):  # kills spread over the whole run (its length measured on this machine)
        out = tmp_path / f"kill{k}"
        process = _start(spec, out)
        time.sleep(duration * (k + rng.random()) / 7)
        process.send_signal(signal.SIGKILL)
        process.wait()
        if assert_sound_folder(out):  # no partial file under a final name; run.json means complete
            assert np.array_equal(np.load(out / "homographies.npy"), expected)
        elif out.exists() and not forced:  # a retry with --force starts anew (the stale lock is taken over)
            result = run_subprocess("run", spec, "-o", out, "--force")
            assert result.returncode == 0, result.stderr
            assert np.array_equal(np.load(out / "homographies.npy"), expected)
            forced = True
    out = tmp_path / "between-levels"  # and one kill right after a checkpoint, then --resume
    process = _start(spec, out)
    while not list((out / outputs.CHECKPOINTS).glob("level_*.npz")) and process.poll() is None:
        time.sleep(0.01)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert not assert_sound_folder(out)
    result = run_subprocess("run", spec, "-o", out, "--resume")
    assert result.returncode == 0, result.stderr
    assert assert_sound_folder(out)
    assert np.array_equal(np.load(out / "homographies.npy"), expected)


def _interrupted_kernel():
    """What Ctrl-C inside a numba kernel raises: SystemError caused by the interrupt."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as interrupt:
        raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set") from interrupt


@pytest.mark.slow
@pytest.mark.parametrize("stop_after, raised", [(1, "interrupt"), (2, "interrupt"), (1, "in-kernel")])
def test_resume_after_an_interrupted_level_equals_an_uninterrupted_run(reference, tmp_path, monkeypatch,
                                                                       stop_after, raised):
    from photonpano.host import PluginHost
    from photonpano.pipeline import run_pipeline
    from photonpano.spec import load_spec

    spec_path, expected, _ = reference
    host = PluginHost()
    spec = load_spec(spec_path, host)
    save = outputs.RunFolder.save_checkpoint

    def interrupt(self, checkpoint):
        save(self, checkpoint)
        if checkpoint.level == stop_after:
            if raised == "in-kernel":
                _interrupted_kernel()
            raise KeyboardInterrupt

    monkeypatch.setattr(outputs.RunFolder, "save_checkpoint", interrupt)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(spec, out, host)
    assert not (out / "run.json").exists() and not (out / outputs.LOCK).exists()
    assert sorted(p.name for p in (out / outputs.CHECKPOINTS).iterdir()) == [f"level_{stop_after}.npz"]
    monkeypatch.setattr(outputs.RunFolder, "save_checkpoint", save)
    summary = run_pipeline(spec, out, host, resume=True).summary
    assert summary["resumed_after_level"] == stop_after and len(summary["levels"]) == 3
    assert np.array_equal(np.load(out / "homographies.npy"), expected)
    assert assert_sound_folder(out) and not (out / outputs.CHECKPOINTS).exists()


@pytest.mark.slow
def test_ctrl_c_exits_promptly_and_keeps_the_checkpoints(reference, tmp_path):
    spec, expected, _ = reference
    out = tmp_path / "out"
    with open(tmp_path / "stderr.txt", "w+") as stderr:
        process = _start(spec, out, stderr)
        while not list((out / outputs.CHECKPOINTS).glob("level_*.npz")) and process.poll() is None:
            time.sleep(0.01)
        time.sleep(0.2)
        start = time.perf_counter()
        process.send_signal(signal.SIGINT)
        code = process.wait(timeout=30)
        stderr.seek(0)
        assert code == 130, stderr.read()[-3000:]
    assert time.perf_counter() - start < 3.0  # within a second or so on an idle machine
    assert not assert_sound_folder(out) and not (out / outputs.LOCK).exists()
    assert list((out / outputs.CHECKPOINTS).glob("level_*.npz"))
    result = run_subprocess("run", spec, "-o", out, "--resume")
    assert result.returncode == 0, result.stderr
    assert np.array_equal(np.load(out / "homographies.npy"), expected)


_COMPILE_THEN_WAIT = """
import os, signal, sys, threading, time, traceback
import numba
import numpy as np
from photonpano.faults import interrupts_outside_compilers
""" + COMPILED_AT_FIRST_CALL + """
threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()  # lands while numba compiles (~0.3 s)
try:
    with interrupts_outside_compilers():
        kernel(np.ones(4))
        sys.stdout.write("compiled\\n")  # one write: print() writes its text and its newline apart
        time.sleep(5)
except KeyboardInterrupt as interrupt:
    inside = any(frame.f_code.co_filename.startswith(os.path.dirname(numba.__file__))
                 for frame, _ in traceback.walk_tb(interrupt.__traceback__))
    print("interrupted inside numba" if inside else "interrupted", flush=True)
    print("restored" if signal.getsignal(signal.SIGINT) is signal.default_int_handler else "not restored")
    sys.exit(130)
"""


def test_ctrl_c_while_numba_compiles_waits_for_the_compile_and_is_not_lost(tmp_path):
    # unheld, the interrupt lands in numba or in a callback from LLVM, where it is lost (the
    # program goes on) or leaves LLVM half-built (a segmentation fault on the way out)
    script = tmp_path / "compile.py"
    script.write_text(_COMPILE_THEN_WAIT)
    start = time.perf_counter()
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60,
                            preexec_fn=sigint_as(signal.SIG_DFL), env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    assert result.returncode == 130, result.stderr
    # the interrupt may come before or after "compiled" is written, never inside numba
    assert result.stdout.split()[-2:] == ["interrupted", "restored"] and "inside" not in result.stdout, result.stdout
    assert "Exception ignored" not in result.stderr
    assert time.perf_counter() - start < 5  # the interrupt came right after the compile, not after the sleep


def test_ctrl_c_ignored_or_handled_elsewhere_is_left_alone():
    from photonpano.faults import interrupts_outside_compilers

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job of a non-interactive shell
    try:
        with interrupts_outside_compilers():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with interrupts_outside_compilers():
            held = signal.getsignal(signal.SIGINT)
            assert held is not signal.default_int_handler
            with interrupts_outside_compilers():  # nested: the outer block's handler stays
                assert signal.getsignal(signal.SIGINT) is held
            assert signal.getsignal(signal.SIGINT) is held
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)
