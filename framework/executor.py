"""Executors: where independent pieces of work (groups, pairs, chunks) run.

One setting in the spec, ``executor: serial | threads | dask`` with ``workers: N`` (and
``dask_address``), selects the executor for the whole pipeline. Stages call
:meth:`Executor.map` on independent tasks. :class:`DaskExecutor` runs them on a Dask
cluster (https://distributed.dask.org): a local cluster of ``workers`` processes, or an
existing scheduler; its tasks must be process-safe (see :class:`DaskExecutor`).

The heavy work inside tasks (OpenCV warps, feature extraction, the numba photon
kernels) releases the GIL, so threads scale over cores. To avoid oversubscription,
OpenCV's own thread pool and the BLAS's are set to one thread while a threaded executor runs.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterable

__all__ = ["Executor", "SerialExecutor", "ThreadExecutor", "DaskExecutor", "make_executor", "Cancelled",
           "pure_task", "process_safe"]

log = logging.getLogger("photonpano")


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
    in_process: bool = True
    """Tasks run in the calling process (and may share its files and memory)."""

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
    """Runs tasks on a pool of ``workers`` threads (OpenCV and the BLAS kept to one thread each).

    Args:
        workers: number of threads (>= 1).
    """

    def __init__(self, workers: int) -> None:
        import cv2
        from threadpoolctl import threadpool_limits

        self.workers = max(1, workers)
        self.cancelled = threading.Event()
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="photonpano")
        self._cv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        # OpenBLAS's own threads, called from several of ours at once, run 2.4x slower
        # (the SIFT matcher's products, IntegralL2Matcher); restored by close()
        self._blas = threadpool_limits(limits=1, user_api="blas")

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
        """Shut the pool down and restore OpenCV's and the BLAS's thread counts.

        After a plugin call hung (:mod:`photonpano.watchdog`) the pool is not waited for:
        its stuck thread would never be joined.
        """
        import cv2

        from .watchdog import hung

        if self._pool is not None:
            self._pool.shutdown(wait=not hung(), cancel_futures=True)
            self._pool = None
            cv2.setNumThreads(self._cv_threads)
            self._blas.restore_original_limits()


class DaskExecutor(Executor):
    """Runs tasks on a Dask cluster: a local one of ``workers`` processes, or an existing scheduler.

    Tasks travel to the workers with cloudpickle: the function is scattered to the
    cluster once per :meth:`map` (not shipped with every task), the items one per task,
    and the results come back in order. Workers must have photonpano installed and see
    the files the tasks read (file-backed sources pickle as "reopen this path", see
    :class:`photonpano.streaming.ReopenOnPickle`). A task runs in another process, so it
    must be *process-safe*: it returns its result and changes nothing else.
    :func:`process_safe` tells a function nested in another that uses the enclosing
    function's variables (the usual way a task writes into its caller's arrays or
    lists): such tasks run in the calling process, one after another, with a warning
    naming them once, so their results stay correct.

    Each worker runs one task at a time with OpenCV limited to one thread
    (``threads_per_worker=1``). Requires the ``dask`` extra
    (``pip install 'photonpano[dask]'``).

    Args:
        workers: worker processes of the local cluster (0: one per CPU core); ignored
            when ``address`` is given.
        address: a running scheduler, e.g. ``"tcp://10.0.0.5:8786"`` (the spec's
            ``dask_address``); None starts a local cluster on 127.0.0.1.
        timeout_s: seconds to wait for the scheduler to accept a connection, and again
            for its handshake (:func:`photonpano.dask_probe.check_scheduler`).

    Attributes:
        client: the ``distributed.Client``.
        dashboard_link: the URL of Dask's dashboard (its pages need ``bokeh>=3.1``), or
            None when the scheduler runs none (``dask scheduler --no-dashboard``).

    Raises:
        MissingDependency: dask.distributed is not installed.
        SpecError: the scheduler at ``address`` cannot be reached, or what answers there
            is not a Dask scheduler (names ``dask_address``).
    """

    in_process = False

    def __init__(self, workers: int = 0, address: str | None = None, timeout_s: float = 10.0) -> None:
        from .errors import MissingDependency, SpecError

        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:
            raise MissingDependency("executor 'dask' needs dask.distributed: pip install 'photonpano[dask]'") from exc
        self._cluster = None
        self._warned: set[str] = set()
        if address:
            from .dask_probe import check_scheduler

            check_scheduler(address, timeout_s)  # a web server or a silent port: one line, not 3 EiB or a hang
            try:
                self.client = Client(address, timeout=timeout_s, set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                raise SpecError(f"dask_address: no Dask scheduler answers at {address!r} within {timeout_s:g} s "
                                f"({type(exc).__name__}: {exc})") from None
        else:
            import dask

            # distributed sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which makes every large
            # numpy allocation a fresh mmap: +45 % wall time on a 3 000-frame run (5 s of system time)
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
                self._cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                                             processes=True, host="127.0.0.1", dashboard_address=":0",
                                             silence_logs=logging.CRITICAL)
            self.client = Client(self._cluster, set_as_default=False)
        self.client.register_plugin(_one_thread_opencv(), name="photonpano-opencv-threads")
        self.workers = max(1, sum(self.client.nthreads().values()))
        services = self.client.scheduler_info().get("services", {})
        self.dashboard_link = self.client.dashboard_link if "dashboard" in services else None
        where = f"scheduler {address}" if address else f"local Dask cluster of {self.workers} worker processes"
        log.info(f"executor dask: {where}; dashboard: {self.dashboard_link or 'none'}")

    def map(self, fn: Callable[..., Any], *items: Iterable[Any],
            done: Callable[[Any], None] | None = None) -> list[Any]:
        """Run ``fn`` over the items on the cluster and return the results in order.

        ``done`` (see :meth:`Executor.map`) is called here with each result, in order.
        Exceptions raised by a task propagate to the caller (the first in item order);
        if the caller is interrupted, the tasks not finished are cancelled. In a guarded
        run, a plugin call of a task that does not return within the watchdog's limit
        raises :class:`~photonpano.watchdog.PluginHung` here
        (:func:`~photonpano.watchdog.wait_futures`).
        """
        args = list(zip(*items))
        if not args:
            return []
        from .watchdog import wait_futures

        if not process_safe(fn):
            name = getattr(fn, "__qualname__", repr(fn))
            if name not in self._warned:
                self._warned.add(name)
                log.warning(f"executor dask: {name} uses its caller's variables, so it runs in this process, "
                            "not on the cluster")
            return Executor.map(self, fn, *zip(*args), done=done)
        shared = self.client.scatter(fn, hash=False, broadcast=True)  # to each worker once, not with every task
        futures = self.client.map(_call, [shared] * len(args), *zip(*args), pure=False)
        try:
            if done is not None:
                for future in futures:  # in order: progress is as fresh as the slowest task
                    wait_futures(self.client, [future])  # in a guarded run, a hung plugin call: PluginHung
                    done(future.result())
            else:
                wait_futures(self.client, futures)
            return self.client.gather(futures)
        except _Carried as carried:  # a plugin's BaseException, raised here (not in Dask's event loop)
            self.client.cancel(futures)
            raise carried.original.with_traceback(carried.__traceback__) from None
        except BaseException:
            self.client.cancel(futures)
            raise
        finally:
            shared.release()

    def close(self) -> None:
        """Close the client and the local cluster it started (idempotent)."""
        if getattr(self, "client", None) is not None:
            self.client.close()
            self.client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


class _Carried(Exception):
    """A task's ``BaseException`` that is not an ``Exception``, carried back as one.

    Dask's client re-raises such an exception in its own event-loop thread, and the
    caller waits forever; :meth:`DaskExecutor.map` raises the original (``original``,
    with the task's traceback) in the caller instead.
    """

    def __init__(self, original: BaseException) -> None:
        super().__init__(f"{type(original).__name__}: {original}")
        self.original = original

    def __reduce__(self) -> tuple[type, tuple[BaseException]]:
        return _Carried, (self.original,)  # back to the caller with the original, not its message


def _call(fn: Callable[..., Any], *args: Any) -> Any:
    """Call a scattered function on a worker (the function arrives as a resolved future).

    Raises:
        _Carried: for a ``BaseException`` that is not an ``Exception``, Ctrl-C and
            ``sys.exit`` excepted (see :class:`_Carried`); other exceptions as raised.
    """
    try:
        return fn(*args)
    except (Exception, KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:
        raise _Carried(exc).with_traceback(exc.__traceback__) from None


def _one_thread_opencv() -> Any:
    """A Dask worker plugin: one OpenCV and one BLAS thread per worker process (the tasks are the parallelism)."""
    from distributed import WorkerPlugin

    class OneThreadOpenCV(WorkerPlugin):
        def setup(self, worker: Any) -> None:
            import cv2
            from threadpoolctl import threadpool_limits

            cv2.setNumThreads(1)
            threadpool_limits(limits=1, user_api="blas")

    return OneThreadOpenCV()


def process_safe(fn: Callable[..., Any]) -> bool:
    """Whether ``fn`` may run in another process.

    A task marked with :func:`pure_task` may. Otherwise, a function nested in another
    that reads or writes the enclosing function's variables (a closure:
    ``fn.__closure__`` is set) is the usual way tasks fill their caller's arrays or
    lists; in another process those changes would be lost. Module functions, lambdas
    and nested functions without free variables, bound methods and
    ``functools.partial`` of them are process-safe by this test (their arguments travel
    by pickle; methods must not rely on changing their object).

    Args:
        fn: a task function.

    Returns:
        True for a pure task; else False if ``fn`` (or the function a ``partial`` wraps)
        is a closure, else True.
    """
    while isinstance(fn, functools.partial):
        fn = fn.func
    return bool(getattr(fn, "pure_task", False)) or not getattr(fn, "__closure__", None)


def make_executor(kind: str = "serial", workers: int = 0, address: str | None = None) -> Executor:
    """Build an executor.

    Args:
        kind: ``"serial"``, ``"threads"`` or ``"dask"``.
        workers: threads for ``"threads"``, worker processes of the local Dask cluster
            for ``"dask"``; 0 means one per CPU core.
        address: ``"dask"`` only: a running scheduler (the spec's ``dask_address``);
            None starts a local cluster.

    Raises:
        ValueError: for an unknown kind.
        SpecError: the scheduler at ``address`` does not answer.
        MissingDependency: ``"dask"`` without dask.distributed installed.
    """
    if kind == "serial":
        return SerialExecutor()
    if kind == "threads":
        return ThreadExecutor(workers or os.cpu_count() or 1)
    if kind == "dask":
        return DaskExecutor(workers, address)
    raise ValueError(f"unknown executor {kind!r}; expected 'serial', 'threads' or 'dask'")
