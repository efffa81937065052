"""Executors: where independent pieces of work (groups, pairs, chunks) run.

One setting in the spec, ``executor: serial | threads`` with ``workers: N``, selects the
executor for the whole pipeline. Stages call :meth:`Executor.map` on independent tasks;
this is the seam where a distributed engine (processes, a cluster) can plug in later by
implementing the same method.

The heavy work inside tasks (OpenCV warps, feature extraction, the numba photon
kernels) releases the GIL, so threads scale over cores. To avoid oversubscription,
OpenCV's own thread pool is set to one thread while a threaded executor runs.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterable

__all__ = ["Executor", "SerialExecutor", "ThreadExecutor", "make_executor", "Cancelled", "pure_task"]


def pure_task(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Mark a task function as process-safe: it returns its result and changes nothing else.

    Such a task may run in another process (a Dask worker): what it reads travels there
    by pickle (file-backed sources as "reopen this path"), and only its return value
    comes back. A task that fills its caller's arrays or lists, or calls a progress
    callback, is not pure; report progress with :meth:`Executor.map`'s ``done`` instead.
    Returns ``fn`` itself, with ``fn.pure_task = True``.
    """
    fn.pure_task = True  # type: ignore[attr-defined]
    return fn


class Cancelled(Exception):
    """Raised inside a task when its executor was cancelled (the caller was interrupted)."""


class Executor:
    """Runs a function over independent items and returns the results in order."""

    workers: int = 1
    cancelled: threading.Event | None = None

    def raise_if_cancelled(self) -> None:
        """Raise :class:`Cancelled` if the caller was interrupted: long tasks call this between chunks.

        Raises:
            Cancelled: once :meth:`map` saw an exception (e.g. Ctrl-C) in the caller.
        """
        if self.cancelled is not None and self.cancelled.is_set():
            raise Cancelled("the run was interrupted")

    def map(self, fn: Callable[..., Any], *items: Iterable[Any],
            done: Callable[[Any], None] | None = None) -> list[Any]:
        """Return ``[fn(*args) for args in zip(*items)]``, in the order of the items.

        Args:
            fn: the task function (see :func:`pure_task` for what may run elsewhere).
            *items: one iterable per argument of ``fn``.
            done: called with each result as its task finishes, in this process (e.g.
                to advance a progress bar); None: nothing is called.
        """
        results = []
        for args in zip(*items):
            results.append(fn(*args))
            if done is not None:
                done(results[-1])
        return results

    def __reduce__(self) -> tuple[Any, tuple[()]]:
        # a task that holds its executor (to check for cancellation) travels to another
        # process with a serial one: the workers' pool stays where it is
        return SerialExecutor, ()

    def close(self) -> None:
        """Release the workers (idempotent)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SerialExecutor(Executor):
    """Runs every task in the calling thread."""


class ThreadExecutor(Executor):
    """Runs tasks on a pool of ``workers`` threads (OpenCV kept to one thread each).

    Args:
        workers: number of threads (>= 1).
    """

    def __init__(self, workers: int) -> None:
        import cv2

        self.workers = max(1, workers)
        self.cancelled = threading.Event()
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="photonpano")
        self._cv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)

    def map(self, fn: Callable[..., Any], *items: Iterable[Any],
            done: Callable[[Any], None] | None = None) -> list[Any]:
        """Run ``fn`` over the items on the pool; exceptions propagate to the caller.

        ``done`` (see :meth:`Executor.map`) is called from the worker threads. If the
        caller is interrupted (Ctrl-C) or a task fails, the tasks not started are
        cancelled and running ones see :meth:`raise_if_cancelled` fire, so the pool
        drains in well under a second instead of finishing its queue.
        """
        futures = [self._pool.submit(fn, *args) for args in zip(*items)]
        if done is not None:
            for future in futures:
                future.add_done_callback(lambda f: None if f.cancelled() or f.exception() else done(f.result()))
        try:
            return [future.result() for future in futures]
        except BaseException as exc:
            if not isinstance(exc, Exception):  # interrupted: running tasks stop at their next check
                self.cancelled.set()
            for future in futures:
                future.cancel()
            raise

    def close(self) -> None:
        """Shut the pool down and restore OpenCV's thread count."""
        import cv2

        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
            cv2.setNumThreads(self._cv_threads)


def make_executor(kind: str = "serial", workers: int = 0) -> Executor:
    """Build an executor.

    Args:
        kind: ``"serial"`` or ``"threads"``.
        workers: threads for ``"threads"``; 0 means one per CPU core.

    Raises:
        ValueError: for an unknown kind.
    """
    if kind == "serial":
        return SerialExecutor()
    if kind == "threads":
        return ThreadExecutor(workers or os.cpu_count() or 1)
    raise ValueError(f"unknown executor {kind!r}; expected 'serial' or 'threads'")
