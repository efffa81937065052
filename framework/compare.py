"""Compare locators: the same pipeline and capture, one run per registration backend.

``photonpano compare INPUT --locators opencv-sift,opencv-ecc -o OUT`` runs the motion
estimation of one spec once per locator on the *same* opened capture, and writes:

- ``compare.json``: per locator, per level: trajectory RMSE against ground truth (when
  the source knows it), registration failures (consecutive pairs bridged), pairs tried
  and used, locate and level wall times, feature-cache hits and misses; or the error
  that stopped the run;
- ``compare.md``: the same as a Markdown table (what ``docs/locators.md`` shows);
- ``compare.png``: trajectory RMSE and locate time per level, one line per locator;
- ``<locator>/homographies.npy``: each run's (T, 3, 3) frame-to-panorama homographies.

The folder is a :class:`~photonpano.outputs.RunFolder` (atomic files, a manifest, a
lock, never a write through a symbolic link) whose final file is ``compare.json``:
until it appears the comparison is not finished. Each finished locator's row and
homographies are kept in ``checkpoints/locator_<i>.npz`` (``i``: its place in the list);
``--resume`` reuses them and runs only the locators that had not finished, so a
comparison killed at any moment and resumed writes the same homographies as one that
ran through.

By default each backend registers pairs of merged frames at *every* level (the
``pairwise`` scheme, the paper's; the ``mosaic`` scheme, which registers levels >= 2
against the panorama with its own locator, is not used), so the table compares the
backends themselves. With ``refine=True`` the spec's ``level_schemes`` are kept: the table
then compares whole pipelines as ``photonpano run`` would execute them (each backend at
the pairwise levels, the mosaic locator after). The stages are built by the same
:class:`~photonpano.reconstruction.Stages` as ``photonpano run``. Runs use the spec's executor.
The panorama is not assembled (it does not depend on the locator beyond the
homographies); run ``photonpano run`` with the chosen locator for it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel

from .errors import PhotonpanoError
from .host import PluginHost
from .outputs.checkpoint import CHECKPOINTS

__all__ = ["compare_locators", "markdown_table", "plot_comparison", "write_comparison", "COMPARE_JSON"]

COMPARE_JSON = "compare.json"
"""The final file of a comparison (written last: its presence means the comparison is complete)."""


def compare_locators(base: dict[str, Any], locators: list[str], host: PluginHost, folder: Any = None,
                     *, origin: str = "compare", source: Any = None, log: Any = None,
                     on_row: Any = None, refine: bool = False) -> list[dict[str, Any]]:
    """Run the pipeline's motion estimation once per locator on one capture.

    Args:
        base: a spec mapping (its ``locator`` section is replaced by each key in turn;
            the rest, source included, is shared).
        locators: locator plugin keys, each optionally with overrides as
            ``key:field=value:field=value`` (values parsed as YAML).
        host: the plugin host.
        folder: a :class:`~photonpano.outputs.RunFolder` (opened with
            ``final=COMPARE_JSON``) receiving each finished locator's row and homographies
            as ``checkpoints/locator_<i>.npz``, for :func:`write_comparison` and
            ``--resume``; when it is resumed, the locators found there (same spec and
            locator key) are not run again. None: write nothing.
        origin: name used in spec error messages.
        source: an already opened capture to reuse (None: built from the spec once).
        log: optional callable receiving one progress line per finished level and run.
            Inside :func:`photonpano.progress.reporting`, each locator's levels also
            report progress as tasks ``"<locator>: level k: merge + locate"``.
        on_row: optional callable receiving the rows so far after each locator (e.g.
            to show partial results of a long comparison).
        refine: keep the spec's ``level_schemes`` (False: every level registers pairs
            with the compared locator).

    Returns:
        One row per locator: ``{"locator", "spec", "status", "levels": [...],
        "trajectory_rmse_px", "failed_pairs", "locate_s", "total_s"}``, where
        ``status`` is ``"ok"`` or the error message; ``levels`` holds per-level
        statistics (see :meth:`photonpano.records.LevelResult.statistics`) plus
        ``trajectory_rmse_px`` and ``cache``.

    A locator whose spec is invalid, whose extra is missing or whose run fails is
    reported in its row (``status``), not raised.

    Raises:
        OutputError: resuming a comparison whose cached locator was run with another
            spec or locator key (one line naming the file), or a write failed.
    """
    rows: list[dict[str, Any]] = []
    for index, item in enumerate(locators):
        key = json.dumps({"locator": item, "spec": base, "refine": refine}, sort_keys=True, default=str)
        cached = _cached_row(folder, index, key) if folder is not None and folder.resume else None
        if cached is not None:
            rows.append(cached)
            if log:
                log(f"{item}: reused from the interrupted comparison")
        else:
            source, homographies = _compare_one(item, base, host, origin, source, log, rows, refine)
            if folder is not None:
                _cache_row(folder, index, key, rows[-1], homographies)
        if on_row is not None:
            on_row(rows)
    return rows


def _cache_name(index: int) -> str:
    return f"{CHECKPOINTS}/locator_{index}.npz"


def _cache_row(folder: Any, index: int, key: str, row: dict[str, Any], homographies: np.ndarray | None) -> None:
    """Write one locator's row and homographies into ``checkpoints/locator_<index>.npz``, atomically."""
    arrays = {"key": np.frombuffer(key.encode(), np.uint8),
              "row": np.frombuffer(json.dumps(row, default=_json_value).encode(), np.uint8),
              "homographies": np.zeros((0, 3, 3)) if homographies is None else homographies}

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as handle:
            np.savez(handle, **arrays)

    folder.write_with(_cache_name(index), write)


def _read_cache(folder: Any, index: int) -> tuple[str, dict[str, Any], np.ndarray] | None:
    """Return ``(key, row, homographies)`` cached for locator ``index``; None if absent or unreadable."""
    from .outputs.files import regular_file_inside

    path = regular_file_inside(folder.root, _cache_name(index))
    if path is None:
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return data["key"].tobytes().decode(), json.loads(data["row"].tobytes().decode()), data["homographies"]
    except (OSError, ValueError, KeyError, EOFError):  # damaged: run the locator again (the file is replaced)
        return None


def _cached_row(folder: Any, index: int, key: str) -> dict[str, Any] | None:
    """The row of locator ``index`` from an interrupted comparison, if it ran with the same ``key``."""
    from .errors import OutputError

    cached = _read_cache(folder, index)
    if cached is None:
        return None
    if cached[0] != key:
        raise OutputError(f"--resume: {folder.root / _cache_name(index)} was written with another spec or "
                          "locator list; resume with the same command, or pass --force to start anew")
    return cached[1]


def _compare_one(item: str, base: dict[str, Any], host: PluginHost, origin: str, source: Any, log: Any,
                 rows: list[dict[str, Any]], refine: bool) -> tuple[Any, np.ndarray | None]:
    """Run one locator (see :func:`compare_locators`); append its row; return the source and homographies."""
    from .executor import make_executor
    from .faults import interrupts_outside_compilers
    from .metrics import source_trajectory_error
    from .progress import start_task
    from .reconstruction import Stages
    from .spec import apply_overrides, validate_spec
    from .watchdog import guarding

    key, *options = item.split(":")
    label = item
    data = apply_overrides({k: v for k, v in base.items() if k != "locator"},
                           [f"locator={key}", *(f"locator.{o}" for o in options)])
    if not refine:
        data = {k: v for k, v in data.items() if k != "refine_locator"}
        data["level_schemes"] = ["pairwise"]
    row: dict[str, Any] = {"locator": label, "status": "ok", "levels": []}
    rows.append(row)
    try:
        spec = validate_spec(data, host, origin=f"{origin} ({label})")
        type(spec.locator).check_available()
    except PhotonpanoError as exc:
        row["status"] = str(exc)
        return source, None
    row["spec"] = spec.locator.model_dump(mode="json")
    row["level_schemes"] = list(spec.level_schemes)
    if source is None:
        source = spec.source.build()
    t0 = time.perf_counter()
    try:
        stages = Stages(spec, source)

        def on_level(result: Any) -> None:
            stats = stages.level_statistics(result)
            stats["cache"] = stats.pop("locator_cache", {})
            row["levels"].append(stats)
            if log:
                log(f"{label}: level {stats['level']}: locate {stats['timings_s'].get('locate', 0):.1f} s, "
                    f"{stats['failed_pairs']} failed pairs" + _rmse_text(stats.get("trajectory_rmse_px")))

        with guarding(host), interrupts_outside_compilers(), \
                make_executor(spec.executor, spec.workers, spec.dask_address) as executor:
            homographies = stages.estimate_motion(executor, on_level=on_level,
                                                  progress=lambda task, total: start_task(f"{label}: {task}", total))
    except PhotonpanoError as exc:
        row["status"] = str(exc)
        return source, None
    finally:
        row["total_s"] = time.perf_counter() - t0
    if source.ground_truth is not None:
        row["trajectory_rmse_px"] = source_trajectory_error(homographies, source).rmse_px
    row["failed_pairs"] = sum(level["failed_pairs"] for level in row["levels"])
    row["locate_s"] = sum(level["timings_s"].get("locate", 0.0) for level in row["levels"])
    if log:
        log(f"{label}: done in {row['total_s']:.1f} s" + _rmse_text(row.get("trajectory_rmse_px")))
    return source, homographies


def _rmse_text(rmse: float | None) -> str:
    return f", RMSE {rmse:.3f} px" if rmse is not None else ""


def _safe(label: str) -> str:
    return "".join(c if c.isalnum() or c in "-_.=" else "_" for c in label)


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """Return the comparison as a Markdown table, one row per locator.

    Columns: final trajectory RMSE (px), RMSE per level, failed (bridged) consecutive
    pairs per level, locate time per level (s), total motion-estimation time (s),
    feature-cache hits/misses summed over levels.
    """
    lines = ["| locator | RMSE (px) | RMSE per level (px) | failed pairs per level "
             "| locate time per level (s) | total (s) | cache hits/misses |",
             "| --- | ---: | --- | --- | --- | ---: | --- |"]
    for row in rows:
        if row["status"] != "ok":
            lines.append(f"| `{row['locator']}` | – | {row['status'].splitlines()[0]} | | | | |")
            continue
        levels = row["levels"]
        rmse = row.get("trajectory_rmse_px")
        per_level = " / ".join(f"{lv['trajectory_rmse_px']:.3f}" for lv in levels
                               if "trajectory_rmse_px" in lv)
        failed = " / ".join(str(lv["failed_pairs"]) for lv in levels)
        locate = " / ".join(f"{lv['timings_s'].get('locate', 0):.1f}" for lv in levels)
        hits = sum(lv.get("cache", {}).get("hits", 0) for lv in levels)
        misses = sum(lv.get("cache", {}).get("misses", 0) for lv in levels)
        cache = f"{hits}/{misses}" if hits or misses else "–"
        final = "–" if rmse is None else f"{rmse:.3f}"
        lines.append(f"| `{row['locator']}` | {final} | {per_level or '–'} | "
                     f"{failed} | {locate} | {row['total_s']:.1f} | {cache} |")
    return "\n".join(lines) + "\n"


def plot_comparison(rows: list[dict[str, Any]], path: Path) -> None:
    """Plot trajectory RMSE (if known) and locate time per level, one line per locator."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for row in rows:
        if row["status"] != "ok" or not row["levels"]:
            continue
        levels = [lv["level"] for lv in row["levels"]]
        if all("trajectory_rmse_px" in lv for lv in row["levels"]):
            axes[0].semilogy(levels, [lv["trajectory_rmse_px"] for lv in row["levels"]], "o-",
                             label=row["locator"])
        axes[1].plot(levels, [lv["timings_s"].get("locate", 0) for lv in row["levels"]], "o-",
                     label=row["locator"])
    axes[0].set(xlabel="level", ylabel="trajectory RMSE (px)", title="error against ground truth")
    axes[1].set(xlabel="level", ylabel="locate time (s)", title="registration time")
    from matplotlib.ticker import MaxNLocator

    for axis in axes:
        axis.grid(alpha=0.3)
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_comparison(rows: list[dict[str, Any]], folder: Any, spec_data: dict[str, Any] | BaseModel) -> None:
    """Write the comparison into ``folder`` and finish it; ``compare.json`` comes last.

    Writes ``<locator>/homographies.npy`` for each locator that finished (from its
    ``checkpoints/locator_<i>.npz``, see :func:`compare_locators`), ``compare.md``,
    ``compare.png``, then commits the folder with ``compare.json`` (which drops the
    checkpoints). Every file is written atomically, never through a symbolic link.

    Args:
        rows: from :func:`compare_locators` run with this ``folder``, in locator order.
        folder: the :class:`~photonpano.outputs.RunFolder`, opened with ``final=COMPARE_JSON``.
        spec_data: the base spec (recorded in ``compare.json``).

    Raises:
        OutputError: a component of an output name is a symbolic link, or an OS error
            (full disk, read-only folder); one line naming the file.
    """
    for index, row in enumerate(rows):
        cached = _read_cache(folder, index) if row["status"] == "ok" else None
        if cached is not None and len(cached[2]):
            folder.save_npy(f"{_safe(row['locator'])}/homographies.npy", cached[2])
    folder.write_text("compare.md", markdown_table(rows))
    folder.write_with("compare.png", lambda tmp: plot_comparison(rows, tmp))
    data = spec_data.model_dump(mode="json") if isinstance(spec_data, BaseModel) else spec_data
    folder.commit(json.dumps({"spec": data, "runs": rows}, indent=2, default=_json_value))


def _json_value(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
