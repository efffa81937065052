"""Faults of a run: the plugin to blame for an unexpected exception, and Ctrl-C where it is safe.

A bug in plugin code (a locator, an observer hook, ``source_for_input``) surfaces as
an arbitrary exception from deep inside the pipeline. :func:`plugin_failure` walks its
traceback from the innermost frame outwards to the first frame in a plugin's module,
names that plugin and its stage (or hook), writes the full traceback to a log file and
returns a :class:`~photonpano.errors.PluginError` whose message is one line.

Ctrl-C that lands while a compiled kernel (numba) runs does not arrive as
``KeyboardInterrupt``: the kernel returns with the interrupt pending and CPython raises
``SystemError: ... returned a result with an exception set`` with the interrupt as its
cause. :func:`unwrapped_interrupts` turns it back into the interrupt it is.

Ctrl-C that lands while numba loads a kernel from its cache or compiles one is worse:
the interrupt is raised in Python code that LLVM calls back (llvmlite's object cache)
or in llvmlite's clean-up, where it is lost (the run goes on as if no key was pressed)
or leaves LLVM's state half-built (the process dies with a segmentation fault on its
way out; measured: a first call of three cached kernels interrupted at random moments
of its 0.3 s, 2 of 150 crashed and 20 went on). :func:`interrupts_outside_compilers`
makes Ctrl-C wait until numba and llvmlite have returned, for the command line
and for a run started from Python.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import tempfile
import threading
import traceback
from collections.abc import Iterator
from types import FrameType
from typing import Any

from .errors import PluginError

__all__ = ["interrupts_outside_compilers", "plugin_failure", "short_repr", "unwrapped_interrupts"]


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters (bad values can be huge)."""
    text = repr(value) if not isinstance(value, (dict, list, tuple, set)) or len(value) < 50 else (
        f"<{type(value).__name__} of {len(value)} items>")
    return text if len(text) <= limit else f"{text[:limit - 3]}..."


@contextlib.contextmanager
def unwrapped_interrupts() -> Iterator[None]:
    """Re-raise as ``KeyboardInterrupt`` an exception whose cause or context is one.

    Raises:
        KeyboardInterrupt: the block raised an exception caused by Ctrl-C (e.g. the
            ``SystemError`` of a numba kernel interrupted while it ran), from that exception.
    """
    try:
        yield
    except Exception as exc:
        seen: set[int] = set()
        link: BaseException | None = exc
        while link is not None and id(link) not in seen:
            if isinstance(link, KeyboardInterrupt):
                raise KeyboardInterrupt from exc
            seen.add(id(link))
            link = link.__cause__ or link.__context__
        raise


COMPILERS = ("numba", "llvmlite")
"""Packages inside which Ctrl-C is held back (their state must not be left half-built)."""

RETRY_S = 0.01
"""Seconds after which a held-back Ctrl-C is sent again (until it lands outside :data:`COMPILERS`)."""

_retry: list[threading.Timer] = []


def _in_compiler(frame: FrameType | None) -> bool:
    """Whether ``frame`` or a frame that called it runs code of a package in :data:`COMPILERS`."""
    folders = tuple(os.path.dirname(module.__file__) + os.sep for name in COMPILERS
                    if (module := sys.modules.get(name)) is not None and module.__file__)
    while folders and frame is not None:
        if frame.f_code.co_filename.startswith(folders):
            return True
        frame = frame.f_back
    return False


def _on_interrupt(signum: int, frame: FrameType | None) -> None:
    """``SIGINT`` handler: ``KeyboardInterrupt``, or the signal again in :data:`RETRY_S` inside a compiler.

    Raises:
        KeyboardInterrupt: the main thread runs no numba or llvmlite code.
    """
    if not _in_compiler(frame):
        raise KeyboardInterrupt
    if not any(timer.is_alive() for timer in _retry):
        _retry[:] = [threading.Timer(RETRY_S, os.kill, (os.getpid(), signum))]
        _retry[0].daemon = True
        _retry[0].start()


@contextlib.contextmanager
def interrupts_outside_compilers() -> Iterator[None]:
    """Within the block, Ctrl-C (``SIGINT``) waits while the main thread is inside numba or llvmlite.

    The interrupt is raised as ``KeyboardInterrupt`` as usual, except while numba loads
    or compiles a kernel, where it is sent again every :data:`RETRY_S` seconds until the
    main thread has left :data:`COMPILERS` (a load takes milliseconds, a compile about a
    second). Only Python's own handler is replaced, in the main thread, and put back
    after the block: a ``SIGINT`` that is ignored (a background job of a
    non-interactive shell) or handled by someone else (a notebook's kernel) is left as
    it is, and so is a nested block.
    """
    ours = threading.current_thread() is threading.main_thread() and \
        signal.getsignal(signal.SIGINT) is signal.default_int_handler
    if ours:
        signal.signal(signal.SIGINT, _on_interrupt)
    try:
        yield
    finally:
        if ours and signal.getsignal(signal.SIGINT) is _on_interrupt:
            signal.signal(signal.SIGINT, signal.default_int_handler)  # a held-back interrupt still arrives


def _plugin_modules(host: Any) -> dict[str, tuple[str, str]]:
    """Module name -> (stage or "hooks", plugin key or registered name)."""
    from .stages import STAGES

    owners: dict[str, tuple[str, str]] = {}
    for name, plugin in host.pm.list_name_plugin():
        module = getattr(plugin, "__name__", None) or type(plugin).__module__
        owners.setdefault(module, ("hooks", name))
    for stage in STAGES:
        for key, cls in host.registry(stage).items():
            owners[cls.__module__] = (stage, key)
    return owners


def _culprit(exc: BaseException, host: Any, spec: Any = None) -> tuple[str, str, str | None] | None:
    """Return ``(stage, plugin, hook)`` of the innermost plugin frame of ``exc``, or None."""
    owners = _plugin_modules(host)
    packages: dict[str, list[tuple[str, str]]] = {}
    for module, owner in owners.items():
        packages.setdefault(module.rpartition(".")[0], []).append(owner)
    frames = [(f.f_globals.get("__name__", ""), f.f_code.co_name)
              for f, _ in traceback.walk_tb(exc.__traceback__)]
    hook = next((name for _, name in reversed(frames) if name.startswith("photonpano_")), None)
    for module, _ in reversed(frames):
        if module in owners:
            stage, key = owners[module]
            return stage, key, hook
    for module, _ in reversed(frames):  # a helper module next to plugins (e.g. locators/common.py)
        candidates = packages.get(module.rpartition(".")[0], [])
        chosen = [(s, k) for s, k in candidates if spec is not None and getattr(getattr(spec, s, None),
                                                                                "plugin", None) == k]
        if chosen or len(candidates) == 1:
            stage, key = (chosen or candidates)[0]
            return stage, key, hook
    return None


def plugin_failure(exc: BaseException, host: Any, spec: Any = None) -> PluginError:
    """Describe an unexpected exception as one line; the traceback goes to a log file.

    Args:
        exc: the exception (with its traceback).
        host: the :class:`~photonpano.host.PluginHost` whose plugins may be to blame.
        spec: the validated spec (picks the plugin among helpers shared by several).

    Returns:
        A :class:`PluginError` (``"locator (my-locator): RuntimeError: ... (traceback in
        /tmp/...)"``), or one reporting an internal error when no plugin frame is found.
    """
    try:  # a new file of a unique name (mkstemp: never through a link planted in the shared temp folder)
        fd, name = tempfile.mkstemp(prefix=f"photonpano-{os.getpid()}-", suffix="-traceback.log")
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
        where = f"traceback in {name}; --debug shows it"
    except OSError:
        where = "run with --debug for the traceback"
    message = " ".join(str(exc).split())
    what = f"{type(exc).__name__}: {message[:197]}..." if len(message) > 200 else \
        f"{type(exc).__name__}: {message}" if message else type(exc).__name__
    found = _culprit(exc, host, spec)
    if found is None:
        return PluginError(f"internal error: {what} ({where})")
    stage, key, hook = found
    head = f"plugin {key!r} ({hook})" if stage == "hooks" else f"{stage} ({key})"
    if stage != "hooks" and hook:
        head += f" in {hook}"
    return PluginError(f"{head}: plugin code raised {what} ({where})")
