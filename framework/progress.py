"""Observers that report a run's progress: rich bars (the CLI), tqdm bars (the Python API), logging.

Each is an ordinary observer plugin (it implements the lifecycle hooks of
:mod:`photonpano.hookspecs`) registered by the front end that wants it, never through an
entry point. Every phase longer than a few seconds reports through
``photonpano_progress`` (simulation, levels, panorama, ground-truth report), so every
bar shows an estimate of the time left.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Callable, Iterator

from . import hookimpl

__all__ = ["reporting", "start_task", "RichProgress", "TqdmProgress", "tqdm_class", "LogObserver", "level_line"]

log = logging.getLogger("photonpano")

_host: ContextVar[Any] = ContextVar("photonpano_progress_host", default=None)


@contextmanager
def reporting(host: Any) -> Iterator[None]:
    """Route :func:`start_task` calls made inside the block to ``host``'s progress hook."""
    token = _host.set(host)
    try:
        yield
    finally:
        _host.reset(token)


def start_task(task: str, total: int | None) -> Callable[[int], None]:
    """Announce a long task and return its ``advance(units)`` callable.

    Inside a run (see :func:`reporting`), calls ``photonpano_progress`` on the run's
    plugin host, so plugins (e.g. a source that simulates or decodes for a while) report
    progress without knowing who draws it; outside a run the callable does nothing.
    Call this in the thread that runs the pipeline; the returned callable may be used
    from worker threads, and pickled: a copy in another process (a Dask worker) does
    nothing.

    Args:
        task: a short description, e.g. ``"simulate"``.
        total: the number of work units (frames, groups), or None when unknown.

    Returns:
        ``advance(n)``: report ``n`` more units done.
    """
    host = _host.get()
    if host is not None:
        host.hook.photonpano_progress(task=task, total=total, advance=0)
    return _Advance(host, task, total)


class _Advance:
    """``advance(n)`` of one task; a copy in another process (a Dask worker) does nothing."""

    def __init__(self, host: Any, task: str, total: int | None) -> None:
        self.host, self.task, self.total = host, task, total

    def __call__(self, n: int) -> None:
        if self.host is not None:
            self.host.hook.photonpano_progress(task=self.task, total=self.total, advance=n)

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return _Advance, (None, self.task, self.total)


def level_line(level: Any) -> str:
    """One line summarising a finished level (groups, inliers, failed pairs, time)."""
    s = level.statistics()
    seconds = sum(s["timings_s"].values())
    return (f"level {s['level']}: {s['groups']} groups, median {s['median_inliers']:.0f} inliers, "
            f"{s['failed_pairs']} failed pairs, {seconds:.1f} s")


class RichProgress:
    """Progress bars with elapsed time and ETA on the terminal (rich), one per task."""

    def __init__(self, console: Any = None) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.bars = Progress(TextColumn("{task.description:<26}"), BarColumn(), MofNCompleteColumn(),
                             TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), console=console,
                             transient=False)
        self.tasks: dict[str, Any] = {}

    @hookimpl
    def photonpano_run_start(self, source: Any) -> None:
        """Print the capture's description and start drawing."""
        self.bars.console.print(f"source: {source.name}: {source.n_frames} frames of "
                                f"{source.height}x{source.width}")
        self.bars.start()

    @hookimpl
    def photonpano_progress(self, task: str, total: int | None, advance: int) -> None:
        """Add a bar for a new task, or advance its bar."""
        if task not in self.tasks:
            self.bars.start()
            self.tasks[task] = self.bars.add_task(task, total=total)
        self.bars.advance(self.tasks[task], advance)

    @hookimpl
    def photonpano_level_finished(self, level: Any) -> None:
        """Print the level's one-line summary above the bars."""
        self.bars.console.print(level_line(level))

    @hookimpl
    def photonpano_run_finished(self) -> None:
        """Stop drawing."""
        self.stop()

    def stop(self) -> None:
        """Stop drawing (idempotent)."""
        self.bars.stop()


def tqdm_class() -> Any:
    """The tqdm bar class: ``tqdm.auto``'s (widgets in a notebook) where ipywidgets is installed, else text bars.

    Without ipywidgets a notebook's ``tqdm.auto`` bar warns ``IProgress not found`` and
    draws nothing; the text bar works everywhere.
    """
    import importlib.util

    if importlib.util.find_spec("ipywidgets") is None:
        from tqdm.std import tqdm
    else:
        from tqdm.auto import tqdm
    return tqdm


class TqdmProgress:
    """Progress bars with tqdm (:func:`tqdm_class`: widgets in a notebook with ipywidgets, text otherwise)."""

    def __init__(self) -> None:
        self._tqdm = tqdm_class()
        self.bars: dict[str, Any] = {}

    @hookimpl
    def photonpano_progress(self, task: str, total: int | None, advance: int) -> None:
        """Open a bar for a new task, or advance its bar (closed when complete)."""
        bar = self.bars.get(task)
        if bar is None:
            bar = self.bars[task] = self._tqdm(total=total, desc=task, unit="", dynamic_ncols=True)
        bar.update(advance)
        if bar.total is not None and bar.n >= bar.total:
            bar.close()

    @hookimpl
    def photonpano_run_finished(self) -> None:
        """Stop drawing."""
        self.stop()

    def stop(self) -> None:
        """Close every bar (idempotent)."""
        for bar in self.bars.values():
            bar.close()


class LogObserver:
    """Writes the run's milestones to the ``photonpano`` logger (INFO) and progress (DEBUG)."""

    @hookimpl
    def photonpano_run_start(self, spec: Any, source: Any, out_dir: Any) -> None:
        """Log the capture and output folder (INFO) and the resolved spec (DEBUG)."""
        log.info("run start: source %s (%d frames of %dx%d), output %s", source.name, source.n_frames,
                 source.height, source.width, out_dir)
        log.debug("spec: %s", spec.model_dump(mode="json"))

    @hookimpl
    def photonpano_progress(self, task: str, total: int | None, advance: int) -> None:
        """Log the start of each task (DEBUG)."""
        if advance == 0:
            log.debug("%s: started (%s units)", task, total)

    @hookimpl
    def photonpano_level_finished(self, level: Any) -> None:
        """Log the level's one-line summary (INFO)."""
        log.info(level_line(level))

    @hookimpl
    def photonpano_run_finished(self, summary: dict[str, Any], out_dir: Any) -> None:
        """Log the panorama size and the timings (INFO)."""
        log.info("run finished: panorama %dx%d, timings %s, output %s", summary["panorama"]["width"],
                 summary["panorama"]["height"], summary["timings_s"], out_dir)
