"""A watchdog over the stage calls of a run: a plugin call that does not return in time ends the run, named.

The level loop and the panorama call plugin code (a locator's ``register_pairs`` or ``register_to_template``, a
merger's ``merge``, an interpolator's ``interpolate``, a resampler's ``groups``, a
compositor's ``prepare``/``read``/``feed``/``finish``) through :func:`watched`, which
records the call and its deadline in a table (a dictionary entry: no thread per call).
One daemon thread per process checks the table. When a call passes its deadline it
interrupts the main thread, and :func:`guarding`, around the run, turns that interrupt
into a :class:`PluginHung` error whose one line names the stage, the plugin and the method.

The interrupt is a signal of its own, :data:`SIGNAL` (``SIGUSR2``), sent to the main
thread (``pthread_kill``) and caught by a handler that :func:`guarding` installs there
(and unblocks): the handler raises ``KeyboardInterrupt``, so plugin code and the
executors unwind exactly as on Ctrl-C (a thread pool cancels its queue, a run folder
keeps its checkpoints). A signal, not an exception set on the thread
(``PyThreadState_SetAsyncExc``), because a signal also wakes a blocking wait (a sleep,
``future.result()``, a lock), where a pending exception would wait for the wait to end;
and a signal of the watchdog's own, not ``SIGINT``, because ``SIGINT``'s disposition is
not ours to count on: a background job of a non-interactive shell (``photonpano run ...
&``) starts with it ignored, which left every call unwatched. The handler raises only
for a hang the watchdog reported; any other ``SIGUSR2`` goes to the handler that was
there before (``SIG_DFL``: the default action). While the main thread is inside numba or
llvmlite (a kernel loading or compiling) the interrupt waits until it has left them, as
Ctrl-C does (:mod:`photonpano.faults`). The previous handler is restored when
the run ends, unless a signal sent for a hang may still be on its way (then the inert
handler stays). The command line then exits
at once even if the hung call sits in a worker thread that cannot be joined; if the
main thread does not take the interrupt (plugin code that swallows ``KeyboardInterrupt``,
a C library call that ignores signals), the command line prints the same line and exits
after :data:`GRACE_S` seconds. Code that holds the GIL and never returns (a runaway
regular expression) stops every Python thread, the watchdog's too: only a timeout from
outside the process (``timeout``, a scheduler's limit) ends it.

The limit is ``PHOTONPANO_HOOK_TIMEOUT_S`` seconds (:data:`HOOK_TIMEOUT_S` by default;
``0`` or ``off`` switches the watchdog off). The default is far above any real call: a
call handles one window of merged frames, one chunk of binary frames or one level's
keyframes, and the longest measured (``longest``) take seconds (docs/hooks.md).

Only the main thread of a process arms the watchdog (:func:`guarding` elsewhere, e.g.
a run started in a notebook's background thread, leaves calls unwatched), and only
calls made in that process are watched: tasks a Dask executor runs in other processes
are not (Dask's own timeouts apply there).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

from .errors import PluginError
from .faults import RETRY_S, _in_compiler, _plugin_modules

__all__ = ["HOOK_TIMEOUT_S", "GRACE_S", "ENV", "SIGNAL", "PluginHung", "watched", "guarding", "limit_s", "hung",
           "longest", "exit_if_stuck", "command_line", "running_calls", "wait_futures"]

HOOK_TIMEOUT_S = 600.0
"""Default limit of one plugin stage call, in seconds (10 minutes)."""
GRACE_S = 10.0
"""Seconds the command line waits for a stuck main thread to take the interrupt before it exits anyway."""
ENV = "PHOTONPANO_HOOK_TIMEOUT_S"
"""Environment variable overriding :data:`HOOK_TIMEOUT_S` (seconds; ``0`` or ``off``: no limit)."""
SIGNAL = getattr(signal, "SIGUSR2", None)
"""The signal that interrupts the main thread when a call hangs (its handler: :func:`guarding`); None
where the platform has none (Windows: calls stay unwatched)."""


class PluginHung(PluginError):
    """A plugin stage call did not return within the limit (the message names stage, plugin and method)."""


_lock = threading.RLock()  # re-entrant: the signal handler may run while the main thread holds it
# calls in progress: token -> (deadline, stage, plugin object, method, thread id, limit in seconds)
_calls: dict[int, tuple[float, str, Any, str, int, float]] = {}
_tokens = itertools.count()
_state: dict[str, Any] = {"armed": 0, "pid": None, "host": None, "message": None, "thread": None,
                          "hard_exit": False, "installed": False, "previous": None, "owed": 0}
# installed: guarding's SIGNAL handler is in place; previous: the handler it replaced;
# owed: signals sent for hangs whose handler has not run yet
_running: dict[int, tuple[float, str, Any, str, int]] = {}  # every call in progress: (start, stage, plugin,
# method, thread id), watched or not: what a Dask worker is doing (running_calls)
_stuck: set[int] = set()  # tokens of calls reported as hung that have not returned yet
_taken = threading.Event()
longest: dict[str, float] = {}
"""The longest duration in seconds of each ``"stage.method"`` watched in this process (for choosing a limit)."""


def limit_s() -> float | None:
    """The limit of one call in seconds from ``PHOTONPANO_HOOK_TIMEOUT_S``; None when switched off.

    An unset or unreadable value gives :data:`HOOK_TIMEOUT_S`; ``0``, a negative number,
    ``off`` or ``inf`` switch the watchdog off.
    """
    text = os.environ.get(ENV, "").strip().lower()
    if not text:
        return HOOK_TIMEOUT_S
    if text in ("off", "none", "inf"):
        return None
    try:
        value = float(text)
    except ValueError:
        return HOOK_TIMEOUT_S
    return value if 0 < value < float("inf") else None


@contextlib.contextmanager
def watched(stage: str, plugin: Any, method: str) -> Iterator[None]:
    """Watch one plugin call of a run: past the limit, the run ends with :class:`PluginHung` naming it.

    Args:
        stage: the stage kind (``"locator"``, ``"merger"``, ...).
        plugin: the plugin object called (its ``config.plugin`` names it, else the
            innermost plugin frame of the hung thread, else its class).
        method: the method called (``"register_pairs"``).

    Outside :func:`guarding` in this process (or with the limit switched off) the call
    is not watched; either way its duration updates :data:`longest`.
    """
    limit = limit_s() if _state["armed"] and _state["pid"] == os.getpid() else None
    start = time.monotonic()
    token = next(_tokens)
    with _lock:
        _running[token] = (start, stage, plugin, method, threading.get_ident())
        if limit is not None:
            _calls[token] = (start + limit, stage, plugin, method, threading.get_ident(), limit)
    if limit is not None:
        _start_thread()
    try:
        yield
    finally:
        took = time.monotonic() - start
        with _lock:
            _running.pop(token, None)
            _calls.pop(token, None)
            _stuck.discard(token)
            name = f"{stage}.{method}"
            if took > longest.get(name, 0.0):
                longest[name] = took


@contextlib.contextmanager
def guarding(host: Any = None) -> Iterator[None]:
    """Arm the watchdog for the block (in the main thread) and raise :class:`PluginHung` when a call hangs.

    Args:
        host: the :class:`~photonpano.host.PluginHost`, to name the plugin of a hung
            helper module from the stack (optional).

    Raises:
        PluginHung: a watched call passed the limit (its interrupt arrived here as
            ``KeyboardInterrupt``); one line naming stage, plugin and method.
    """
    if threading.current_thread() is not threading.main_thread() or SIGNAL is None:
        yield  # signal handlers belong to the main thread: calls stay unwatched
        return
    with _lock:
        if not _state["armed"]:
            _state.update(pid=os.getpid(), host=host, message=None)
            _taken.clear()
            _install_handler()
        _state["armed"] += 1
    try:
        yield
    except KeyboardInterrupt:
        message = _state["message"]
        if message is None:
            raise
        _taken.set()
        raise PluginHung(message) from None
    finally:
        with _lock:
            _state["armed"] -= 1
            if not _state["armed"] and not _state["owed"] and _state["installed"] and \
                    _state["previous"] is not None:  # None: a handler set outside Python, which cannot be put back
                signal.signal(SIGNAL, _state["previous"])  # no signal of ours on its way: put it back
                _state["installed"] = False
        if _state["message"] is not None and not _state["armed"]:
            _taken.set()
            _state["message"] = None  # reported: a later run in this process starts clean


def hung() -> bool:
    """Whether a call reported as hung in this process has not returned yet (its thread cannot be joined)."""
    return bool(_stuck)


def exit_if_stuck(code: int) -> None:
    """Exit now with ``code`` if a call hung (a worker thread stuck in it would block a normal exit).

    Called by the command line once it has printed its error; flushes stdout and stderr.
    """
    if hung():
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)


def command_line() -> None:
    """Let the watchdog end the process itself when the main thread does not take the interrupt (CLI only)."""
    _state["hard_exit"] = True


def running_calls() -> list[tuple[str, float]]:
    """The innermost :func:`watched` call of each thread of this process, watched or not, and how long it has run.

    Returns:
        One ``("stage (plugin) in method", seconds)`` per thread inside such a call
        (what :func:`wait_futures` asks each Dask worker).
    """
    now = time.monotonic()
    with _lock:
        innermost = {entry[4]: entry for _, entry in sorted(_running.items())}  # by token: the latest per thread
    return [(f"{stage} ({_plugin_name(plugin, thread)}) in {method}", now - start)
            for start, stage, plugin, method, thread in innermost.values()]


def wait_futures(client: Any, futures: list[Any]) -> None:
    """Wait for Dask futures, watching the plugin calls their tasks make on the workers, in a guarded run.

    A task on a Dask worker runs in another process, out of reach of this process's
    watchdog, so the caller waits here instead: it polls the futures (every 20 ms, no
    data moved) and, every limit's worth of seconds, asks the workers for their
    :func:`running_calls` (``client.run``, answered by the worker's event loop while its
    task thread is stuck); a call running longer than the limit ends the wait with the
    one line of a hung call in this process, plus ``on a Dask worker``. Outside
    :func:`guarding`, or with the limit switched off, returns at once.

    Args:
        client: the ``distributed.Client`` the futures belong to.
        futures: the tasks' futures.

    Returns:
        None, once every future is done (finished, failed or cancelled: the caller
        gathers the results and raises the tasks' errors).

    Raises:
        PluginHung: a plugin call of a task has not returned within the limit (the
            caller cancels the tasks; the worker's thread stays stuck in it).
    """
    limit = limit_s() if _state["armed"] and _state["pid"] == os.getpid() else None
    if limit is None:
        return
    first, check = 0, time.monotonic() + limit
    while True:
        while first < len(futures) and futures[first].done():
            first += 1
        if first == len(futures):
            return
        if time.monotonic() < check:
            time.sleep(0.02)
            continue
        calls = [call for found in client.run(running_calls, on_error="ignore").values()
                 if isinstance(found, list) for call in found]
        name, took = max(calls, key=lambda call: call[1], default=("", 0.0))
        if took >= limit:
            raise PluginHung(f"{name} on a Dask worker did not return within {limit:g} s (hangs?); "
                             f"{ENV} sets the limit")
        check = time.monotonic() + limit - took  # when the longest call so far would pass the limit


def _install_handler() -> None:
    """Install :func:`_on_signal` for :data:`SIGNAL` and unblock it in this (the main) thread; under ``_lock``."""
    assert SIGNAL is not None  # guarding() installs nothing on a platform without it
    if not _state["installed"]:
        _state["previous"] = signal.signal(SIGNAL, _on_signal)
        _state["installed"] = True
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {SIGNAL})  # a mask inherited from the parent would keep it pending


def _on_signal(signum: int, frame: Any) -> None:
    """The main thread's :data:`SIGNAL` handler: ``KeyboardInterrupt`` for a reported hang, else the previous one.

    Inside numba or llvmlite the hang's interrupt is held back and the signal sent again
    in :data:`~photonpano.faults.RETRY_S` seconds, as Ctrl-C is
    (:func:`~photonpano.faults.interrupts_outside_compilers`): raised there it is lost
    or leaves LLVM's state half-built.

    Raises:
        KeyboardInterrupt: a watched call hung and the run is still guarded
            (:func:`guarding` turns it into :class:`PluginHung`).
    """
    with _lock:
        ours = _state["owed"] > 0
        if ours and _state["message"] is not None and _state["armed"] and _in_compiler(frame):
            _send_later()  # still owed: the signal comes back once numba or llvmlite has returned
            return
        if ours:
            _state["owed"] -= 1
        previous = _state["previous"]
    if ours:
        if _state["message"] is not None and _state["armed"]:
            raise KeyboardInterrupt
        return  # the run ended before the signal arrived: nothing to interrupt
    if callable(previous):
        previous(signum, frame)
    elif previous == signal.SIG_DFL and SIGNAL is not None:  # not ours, nor anyone's: the default action
        signal.signal(SIGNAL, signal.SIG_DFL)
        os.kill(os.getpid(), SIGNAL)


def _send_later() -> None:
    """Send :data:`SIGNAL` to the main thread again in :data:`~photonpano.faults.RETRY_S` seconds.

    The signal stays owed; one that cannot be sent (the main thread is gone) is not.
    Called with ``_lock`` held (from :func:`_on_signal`); the timer's thread takes it itself.
    """
    def send(thread: int, signum: int) -> None:
        try:
            signal.pthread_kill(thread, signum)
        except (OSError, ValueError):
            with _lock:
                _state["owed"] -= 1

    main, signum = threading.main_thread().ident, SIGNAL
    if main is None or signum is None:  # never: the handler runs in the main thread, for SIGNAL
        _state["owed"] -= 1
        return
    timer = threading.Timer(RETRY_S, send, (main, signum))
    timer.daemon = True
    timer.start()


def _start_thread() -> None:
    with _lock:
        thread = _state["thread"]
        if thread is not None and thread.is_alive() and _state.get("thread_pid") == os.getpid():
            return
        thread = threading.Thread(target=_watch, name="photonpano-watchdog", daemon=True)
        _state["thread"], _state["thread_pid"] = thread, os.getpid()
    thread.start()


def _watch() -> None:
    while True:
        limit = limit_s() or HOOK_TIMEOUT_S
        time.sleep(min(1.0, limit / 10))
        now = time.monotonic()
        with _lock:
            overdue = sorted(entry for entry in _calls.items() if entry[1][0] <= now)  # by token: innermost last
            for token, _ in overdue:
                _calls.pop(token)  # reported once
                _stuck.add(token)
        if not overdue or _state["message"] is not None or not _state["armed"]:
            continue
        _, stage, plugin, method, thread, limit = overdue[-1][1]
        message = (f"{stage} ({_plugin_name(plugin, thread)}) in {method} did not return within {limit:g} s "
                   f"(hangs?); {ENV} sets the limit")
        main = threading.main_thread().ident  # None only before the main thread started: never here
        with _lock:  # while armed, so the handler is in place
            if not _state["armed"] or main is None or SIGNAL is None:
                continue
            _state["message"] = message
            _state["owed"] += 1
            try:
                signal.pthread_kill(main, SIGNAL)
            except (OSError, ValueError):
                _state["owed"] -= 1
        if not _taken.wait(GRACE_S) and _state["hard_exit"]:
            with contextlib.suppress(Exception):
                sys.stderr.write(f"error: {message}\n")
                sys.stderr.flush()
            os._exit(1)


def _plugin_name(plugin: Any, thread: int) -> str:
    """The plugin key of ``plugin``: its config's, else the innermost plugin frame's on ``thread``, else its class."""
    key = getattr(getattr(plugin, "config", None), "plugin", None)
    if isinstance(key, str):
        return key
    host = _state["host"]
    frame = sys._current_frames().get(thread)
    if host is not None and frame is not None:
        owners = _plugin_modules(host)
        while frame is not None:
            owner = owners.get(frame.f_globals.get("__name__", ""))
            if owner is not None and owner[0] != "hooks":
                return owner[1]
            frame = frame.f_back
        owner = owners.get(type(plugin).__module__)
        if owner is not None:
            return owner[1]
    return type(plugin).__name__
