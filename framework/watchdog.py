"""A watchdog over the stage calls of a run: a plugin call that does not return in time ends the run, named.

The level loop and the panorama call plugin code (a locator's ``register_pairs`` or ``register_to_template``, a
merger's ``merge``, an interpolator's ``interpolate``, a resampler's ``groups``, a
compositor's ``prepare``/``read``/``feed``/``finish``) through :func:`watched`, which
records the call and its deadline in a table (a dictionary entry: no thread per call).
One daemon thread per process checks the table. When a call passes its deadline it
interrupts the main thread (``SIGINT`` to it, which also wakes a blocking wait), and
:func:`guarding`, around the run, turns that interrupt into a :class:`PluginHung` error
whose one line names the stage, the plugin and the method. The command line then exits
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

__all__ = ["HOOK_TIMEOUT_S", "GRACE_S", "ENV", "PluginHung", "watched", "guarding", "limit_s", "hung", "longest",
           "exit_if_stuck", "command_line"]

HOOK_TIMEOUT_S = 600.0
"""Default limit of one plugin stage call, in seconds (10 minutes)."""
GRACE_S = 10.0
"""Seconds the command line waits for a stuck main thread to take the interrupt before it exits anyway."""
ENV = "PHOTONPANO_HOOK_TIMEOUT_S"
"""Environment variable overriding :data:`HOOK_TIMEOUT_S` (seconds; ``0`` or ``off``: no limit)."""


class PluginHung(PluginError):
    """A plugin stage call did not return within the limit (the message names stage, plugin and method)."""


_lock = threading.Lock()
# calls in progress: token -> (deadline, stage, plugin object, method, thread id, limit in seconds)
_calls: dict[int, tuple[float, str, Any, str, int, float]] = {}
_tokens = itertools.count()
_state: dict[str, Any] = {"armed": 0, "pid": None, "host": None, "message": None, "thread": None,
                          "hard_exit": False}
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
    if limit is not None:
        with _lock:
            _calls[token] = (start + limit, stage, plugin, method, threading.get_ident(), limit)
        _start_thread()
    try:
        yield
    finally:
        took = time.monotonic() - start
        with _lock:
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
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield  # the interrupt could not reach this thread: calls stay unwatched
        return
    with _lock:
        if not _state["armed"]:
            _state.update(pid=os.getpid(), host=host, message=None)
            _taken.clear()
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
        _state["message"] = message
        main = threading.main_thread().ident  # None only before the main thread started: never here
        if main is not None:
            with contextlib.suppress(OSError, ValueError):
                signal.pthread_kill(main, signal.SIGINT)
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
        from .faults import _plugin_modules

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
