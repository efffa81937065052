"""``photonpano batch``: many captures at once, one output folder each, on processes or a Dask cluster.

Each input (a capture path as ``photonpano pano`` takes it, a spec file, or the key of
a source that needs no file, e.g. ``simulate``) becomes one job: the whole pipeline
(:func:`photonpano.run`) with ``executor: serial`` inside, writing into
``OUTROOT/<stem of the input>`` (``-2``, ``-3``, ... appended to repeated stems).
Jobs run concurrently:

- ``--set executor=dask``: one Dask task per capture, on a local cluster of
  ``workers`` processes or on the scheduler at ``dask_address`` (its workers must see
  the inputs and OUTROOT: shared storage);
- otherwise: a process pool (:class:`concurrent.futures.ProcessPoolExecutor`) of
  ``workers`` processes (0: one per CPU core).

``executor``, ``workers`` and ``dask_address`` are read from the ``--set`` overrides;
every other override applies to every capture. A failing capture is reported and the
others go on.

Each capture writes through its own :class:`~photonpano.outputs.RunFolder` (atomic files,
``run.json`` last), so a batch killed at any moment leaves no complete-looking partial
run. ``--resume`` then skips the captures whose run finished (reported as reused),
continues the interrupted ones from their last finished level and runs the others: the
outputs equal those of an uninterrupted batch. The process pool's workers end with the
batch process (they watch it), so none keeps writing after a kill.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from .errors import PhotonpanoError

__all__ = ["BatchJob", "BatchResult", "plan_jobs", "run_capture", "run_batch", "summary_table",
           "EXECUTION_FIELDS", "capture_state"]

EXECUTION_FIELDS = ("executor", "workers", "dask_address")
"""Spec fields that choose where the batch runs (read from the overrides, not per capture)."""


@dataclass(frozen=True)
class BatchJob:
    """One capture of a batch.

    Attributes:
        input: the input as given on the command line.
        spec: what :func:`photonpano.run` takes: a spec file path or a mapping; None
            when the input could not be turned into a spec (``error`` says why).
        out_dir: the capture's output folder (absolute).
        error: why the input was refused before running, or None.
    """

    input: str
    spec: Path | dict[str, Any] | None
    out_dir: Path
    error: str | None = None


@dataclass(frozen=True)
class BatchResult:
    """What one capture produced.

    Attributes:
        input: the input as given.
        out_dir: its output folder.
        status: ``"ok"`` or ``"failed"``.
        frames: binary frames reconstructed (0 if it failed).
        levels: levels run (0 if it failed).
        time_s: wall-clock seconds of the run, in the worker.
        error: a one-line reason when it failed, else None.
        reused: the run was already complete in ``out_dir`` (``--resume``): not run again.
    """

    input: str
    out_dir: Path
    status: str
    frames: int = 0
    levels: int = 0
    time_s: float = 0.0
    error: str | None = None
    reused: bool = False


def _stem(text: str) -> str:
    """The output folder name of an input: its file or folder name without suffix."""
    path = Path(text)
    return path.stem or path.name or "capture"


def plan_jobs(inputs: Sequence[str], out_root: Path, host: Any) -> list[BatchJob]:
    """Turn the inputs into jobs with distinct output folders.

    Args:
        inputs: capture paths (anything ``photonpano pano`` reads), spec files
            (``.yaml``/``.yml``) or keys of registered sources (``simulate``).
        out_root: the folder that receives one output folder per input.
        host: the plugin host (claims inputs for sources, lists source keys).

    Returns:
        One :class:`BatchJob` per input, in order; an input that no source reads or
        that does not exist gets ``spec=None`` and its ``error``.
    """
    from .presets import spec_for_capture

    sources = host.registry("source")
    used: set[str] = set()
    jobs = []
    for text in inputs:
        name = stem = _stem(text)
        k = 2
        while name in used:
            name, k = f"{stem}-{k}", k + 1
        used.add(name)
        out_dir = (out_root / name).absolute()
        path = Path(text).absolute()
        try:
            if text in sources and not Path(text).exists():
                spec: Path | dict[str, Any] = {"source": {"plugin": text}}
            elif path.suffix.lower() in (".yaml", ".yml"):
                if not path.is_file():
                    raise PhotonpanoError(f"spec file {text} does not exist")
                spec = path
            else:
                spec = spec_for_capture(path, host)
        except Exception as exc:  # a missing input, or a source plugin's bug: that capture fails
            reason = str(exc) if isinstance(exc, PhotonpanoError) else f"{type(exc).__name__}: {exc}"
            jobs.append(BatchJob(text, None, out_dir, " ".join(reason.split())))
            continue
        jobs.append(BatchJob(text, spec, out_dir))
    return jobs


def capture_state(out_dir: Path) -> str:
    """What ``out_dir`` holds: ``"complete"``, ``"interrupted"`` (a manifest, no run.json) or ``"new"``.

    Never follows a symbolic link (a linked folder or manifest is ``"new"``: the run
    itself then refuses the folder in one line).
    """
    from .outputs import MANIFEST, RUN_JSON

    manifest = out_dir / MANIFEST
    if out_dir.is_symlink() or manifest.is_symlink() or not manifest.is_file():
        return "new"
    run_json = out_dir / RUN_JSON
    return "complete" if run_json.is_file() and not run_json.is_symlink() else "interrupted"


def _reused(job: BatchJob) -> BatchResult | None:
    """The result of a capture whose run finished before (``--resume``), from its ``run.json``; None if unreadable."""
    import json

    from .outputs import RUN_JSON

    try:
        summary = json.loads((job.out_dir / RUN_JSON).read_text())
        return BatchResult(job.input, job.out_dir, "ok", int(summary["source"]["frames"]), len(summary["levels"]),
                           reused=True)
    except (OSError, ValueError, KeyError, TypeError):
        return None


def run_capture(job: BatchJob, overrides: Sequence[str], force: bool, resume: bool = False) -> BatchResult:
    """Run one capture's whole pipeline with the serial executor (a process or Dask task).

    Args:
        job: the capture.
        overrides: ``--set`` strings for every capture (the execution fields are
            replaced by ``executor=serial``).
        force: replace a previous run's outputs in ``job.out_dir``.
        resume: a capture whose run in ``job.out_dir`` is complete is not run again
            (its result comes from its ``run.json``, ``reused``); an interrupted one
            continues from its last finished level; any other runs from the start.

    Returns:
        The capture's :class:`BatchResult`; every exception of the run becomes a
        failed result with a one-line reason (this function does not raise).
    """
    t0 = time.perf_counter()
    if job.spec is None:
        return BatchResult(job.input, job.out_dir, "failed", error=job.error)
    from .api import run

    sets = [o for o in overrides if o.split("=", 1)[0].strip() not in EXECUTION_FIELDS] + ["executor=serial"]
    state = capture_state(job.out_dir) if resume else "new"
    if state == "complete":
        reused = _reused(job)
        if reused is not None:
            return reused
    try:
        summary = run(job.spec, job.out_dir, sets, progress=False, force=force,
                      resume=state != "new").summary
    except Exception as exc:  # any failure of one capture is reported, not raised
        reason = str(exc) if isinstance(exc, PhotonpanoError) else f"{type(exc).__name__}: {exc}"
        return BatchResult(job.input, job.out_dir, "failed", time_s=time.perf_counter() - t0,
                           error=" ".join(reason.split()))
    return BatchResult(job.input, job.out_dir, "ok", int(summary["source"]["frames"]), len(summary["levels"]),
                       time.perf_counter() - t0)


def execution_settings(overrides: Sequence[str], host: Any) -> Any:
    """Validate the execution fields among the overrides; return the validated spec holding them.

    Raises:
        SpecError: a bad ``executor``, ``workers`` or ``dask_address`` (one line naming it).
    """
    from .spec import apply_overrides, validate_spec

    picked = [o for o in overrides if o.split("=", 1)[0].strip() in EXECUTION_FIELDS]
    return validate_spec(apply_overrides({"source": {"plugin": "simulate"}}, picked), host, origin="batch --set",
                         overridden=picked)


def run_batch(jobs: Sequence[BatchJob], overrides: Sequence[str] = (), *, force: bool = False,
              resume: bool = False, host: Any = None, on_result: Callable[[BatchResult], None] | None = None,
              on_start: Callable[[str], None] | None = None) -> list[BatchResult]:
    """Run the jobs concurrently and return their results in job order.

    Args:
        jobs: from :func:`plan_jobs`.
        overrides: ``--set`` strings; ``executor``, ``workers`` and ``dask_address``
            choose where the jobs run (see the module docstring), the others apply to
            every capture.
        force: replace previous outputs in the capture folders.
        resume: skip finished captures and continue interrupted ones (see :func:`run_capture`).
        host: the plugin host used to validate the execution fields.
        on_result: called in this process with each result as it arrives.
        on_start: called with a line describing where the jobs run (the Dask dashboard
            link when there is one).

    Returns:
        One :class:`BatchResult` per job, in job order.

    Raises:
        SpecError: bad execution fields, or a ``dask_address`` with no scheduler.
        MissingDependency: ``executor=dask`` without dask.distributed installed.
    """
    import os

    from .host import PluginHost

    settings = execution_settings(overrides, host or PluginHost())
    runnable = sum(job.spec is not None for job in jobs)
    workers = max(1, min(settings.workers or os.cpu_count() or 1, runnable))
    results: dict[int, BatchResult] = {}
    if settings.executor == "dask":
        from .executor import DaskExecutor

        cluster = DaskExecutor(workers if settings.dask_address is None else 0, settings.dask_address)
        pool: Any = cluster.client.get_executor(pure=False)
        where = f"Dask: {cluster.workers} workers" + (f", dashboard {cluster.dashboard_link}"
                                                       if cluster.dashboard_link else "")
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        cluster = None
        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=exit_with_parent, initargs=(os.getpid(),))
        where = f"{workers} worker processes"
    if on_start is not None:
        on_start(f"{len(jobs)} captures on {where}")
    try:
        futures: dict[Future, int] = {}
        for i, job in enumerate(jobs):
            if job.spec is None:  # refused before running: nothing to ship
                results[i] = run_capture(job, overrides, force, resume)
                if on_result is not None:
                    on_result(results[i])
            else:
                futures[pool.submit(run_capture, job, list(overrides), force, resume)] = i
        for future in as_completed(futures):
            i = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # the worker itself died (killed, out of memory)
                job = jobs[i]
                result = BatchResult(job.input, job.out_dir, "failed", error=f"worker lost: {type(exc).__name__}: "
                                     f"{' '.join(str(exc).split())}")
            results[i] = result
            if on_result is not None:
                on_result(result)
    finally:
        if cluster is None:
            pool.shutdown(wait=True, cancel_futures=True)
        else:
            pool.shutdown(wait=False)
            cluster.close()
    return [results[i] for i in range(len(jobs))]


def exit_with_parent(parent: int, period_s: float = 0.5) -> None:
    """Make this worker process end (exit status 1) within ``period_s`` seconds once process ``parent`` is gone.

    The initializer of the batch's worker processes: a batch killed with SIGKILL cannot
    stop its workers, and an orphaned one would go on writing into a capture folder (and
    hold its lock against ``--resume``). A daemon thread polls the parent pid.
    """
    import os
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        os._exit(1)

    threading.Thread(target=watch, name="photonpano-exit-with-parent", daemon=True).start()


def summary_table(results: Sequence[BatchResult]) -> Any:
    """A rich table of the results: input, output, frames, levels, time, status."""
    from rich.table import Table

    table = Table(title="photonpano batch")
    for name, justify in (("input", "left"), ("output", "left"), ("frames", "right"), ("levels", "right"),
                          ("time (s)", "right"), ("status", "left")):
        table.add_column(name, justify=justify, overflow="fold")
    for r in results:
        table.add_row(r.input, str(r.out_dir), str(r.frames) if r.frames else "-", str(r.levels) if r.levels else "-",
                      f"{r.time_s:.1f}", f"{r.status} (reused)" if r.reused else r.status)
    return table


def main(inputs: Sequence[str], out_root: Path, overrides: Sequence[str], force: bool, quiet: bool,
         host: Any, resume: bool = False) -> int:
    """The ``photonpano batch`` command: run, show one progress bar and the summary table.

    Returns:
        The exit code: 0 if every capture succeeded, 1 otherwise.

    Raises:
        PhotonpanoError: the batch cannot start (no inputs, bad execution settings,
            OUTROOT not a folder or a symbolic link, no scheduler at ``dask_address``).
    """
    from rich.console import Console
    from rich.text import Text

    from .outputs.files import refuse_symlink
    from .progress import RichProgress

    if not inputs:
        raise PhotonpanoError("batch: give at least one input")
    if force and resume:
        raise PhotonpanoError("batch: --force and --resume exclude each other")
    refuse_symlink(out_root, "batch: output folder")  # each capture's folder is refused by its run
    if out_root.exists() and not out_root.is_dir():
        raise PhotonpanoError(f"batch: -o {out_root} is a file; expected a folder")
    errors = Console(stderr=True)
    jobs = plan_jobs(inputs, out_root, host)
    execution_settings(overrides, host)  # fail before creating OUTROOT
    out_root.mkdir(parents=True, exist_ok=True)
    bars = None if quiet else RichProgress(errors)

    def start(where: str) -> None:
        if bars is not None:
            errors.print(where, markup=False)
            bars.bars.start()
            bars.photonpano_progress(task="captures", total=len(jobs), advance=0)

    def done(result: BatchResult) -> None:
        if bars is not None:
            bars.photonpano_progress(task="captures", total=len(jobs), advance=1)
            how = "reused" if result.reused else f"{result.time_s:.1f} s"
            bars.bars.console.print(f"{result.input}: {result.status} ({how})", markup=False)

    try:
        results = run_batch(jobs, overrides, force=force, resume=resume, host=host, on_result=done,
                            on_start=start)
    finally:
        if bars is not None:
            bars.stop()
    Console().print(summary_table(results))
    failed = [r for r in results if r.status != "ok"]
    for r in failed:
        errors.print(Text.assemble(("error:", "red"), f" capture {r.input} failed: {r.error}"), soft_wrap=True)
    return 1 if failed else 0
