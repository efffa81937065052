"""The ``photonpano`` command line.

``run`` a spec, ``pano`` an input with the paper's default spec, ``demo`` on the bundled
photograph, list ``plugins``, ``validate`` a spec and print its JSON ``schema``; the
commands beside the main job (``pose``, ``convert``, ``batch``, ``compare``, ``score``, ``video``) are in
:mod:`photonpano.cli_tools`; the application, its global options and the helpers both
use are in :mod:`photonpano.cli_base` (this module imports ``cli_tools`` to register its
commands; ``cli_tools`` does not import this module).
Expected failures (bad input, bad spec, broken plugin) print one line and exit 1.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, cast

import typer

from .cli_base import (
    ForceOption,
    OutOption,
    ResumeOption,
    SetOption,
    _capture_spec,
    _host,
    _observed,
    _passes_through,
    _plugin_failure,
    app,
    one_line_errors,
)

if TYPE_CHECKING:
    from .plugins.sources.simulate import SimulateConfig


def _execute(spec, out: Path, force: bool, host, resume: bool = False) -> dict[str, Any]:
    import warnings

    from .pipeline import run_pipeline

    for note in host.collisions:  # a third party offering a key or name already taken
        warnings.warn(note, stacklevel=1)
    with _observed(host):
        try:
            return run_pipeline(spec, out, host, force=force, resume=resume).summary
        except BaseException as exc:  # plugin code raising anything, a BaseException subclass too: one line
            if _passes_through(exc):
                raise
            raise _plugin_failure(exc, host, spec) from exc


def _report(summary: dict[str, Any], out: Path) -> None:
    gt = summary.get("ground_truth")
    t = summary["timings_s"]
    typer.echo(f"panorama {summary['panorama']['width']}x{summary['panorama']['height']} written to {out} "
               f"(levels {t['levels']:.1f} s, panorama {t['panorama']:.1f} s)")
    if gt:
        per_level = ", ".join(f"level {row['level']}: {row['trajectory_rmse_px']:.3f}" for row in summary["levels"])
        typer.echo(f"trajectory RMSE vs ground truth (px): {per_level}")
        if "psnr_db" in gt:
            typer.echo(f"panorama PSNR {gt['psnr_db']:.2f} dB; with the true homographies "
                       f"{gt['psnr_true_homographies_db']:.2f} dB (gap {gt['psnr_gap_db']:.2f} dB)")
    unc = summary.get("uncertainty")
    if unc and unc["median_px"] is not None:
        typer.echo(f"predicted per-frame error ({unc['evidence']}): median {unc['median_px']:.3f} px, "
                   f"95th percentile {unc['p95_px']:.3f} px (uncertainty.npy)")
    for note in summary.get("notes", []):
        typer.secho(f"note: {note}", err=True)
    for warning in summary.get("warnings", []):
        typer.secho(f"warning: {warning}", fg=typer.colors.YELLOW, err=True)
    if "status" in summary:
        typer.echo(f"status: {summary['status']} (group size {summary['group_size']['group_size']}: "
                   f"{summary['group_size']['reason']})")


@app.command()
@one_line_errors
def run(spec: Annotated[Path, typer.Argument(help="Pipeline spec (YAML).")], output: OutOption,
        set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False) -> None:
    """Run the pipeline described by a YAML spec."""
    from .spec import load_spec

    host = _host()
    parsed = load_spec(spec, host, set_ or [])
    if getattr(parsed, "pose_estimator", None) is not None:  # experimental: camera poses
        from .cli_tools import execute_pose

        execute_pose(parsed, output, force, host, resume)
        return
    _report(_execute(parsed, output, force, host, resume), output)


@app.command()
@one_line_errors
def pano(input: Annotated[Path, typer.Argument(help="A capture: a .npy photon cube, a folder of SwissSPAD .bin "
                                                 "files, a video, an image folder or a Photron .mraw.")],
         output: OutOption,
         set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False) -> None:
    """Reconstruct a panorama from INPUT with the paper's default settings."""
    from .spec import apply_overrides, validate_spec

    host = _host()
    data = apply_overrides(_capture_spec(input, host), set_ or [])
    parsed = validate_spec(data, host, origin="pano")
    _report(_execute(parsed, output, force, host, resume), output)


@app.command()
@one_line_errors
def demo(output: OutOption, set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False,
         frames: Annotated[int, typer.Option(help="Binary frames to simulate.")] = 20_000) -> None:
    """Simulate a capture from the bundled real photograph and reconstruct it.

    Prints the trajectory error and the panorama PSNR against ground truth.
    """
    from .spec import apply_overrides, validate_spec

    host = _host()
    data = apply_overrides({"source": {"plugin": "simulate", "frames": frames}}, set_ or [])
    parsed = validate_spec(data, host, origin="demo")
    simulated = cast("SimulateConfig", parsed.source)  # the demo's spec names the simulate source
    typer.echo(f"simulating {simulated.frames} binary frames of {simulated.height}x"
               f"{simulated.width} at flux {simulated.flux} from the bundled photo ...")
    _report(_execute(parsed, output, force, host, resume), output)


@app.command()
@one_line_errors
def plugins() -> None:
    """List installed plugins: key, stage, module, distribution, version, status."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    table = Table("key", "stage", "module", "distribution", "version", "status")
    for info in _host().plugin_infos():
        # escape: rich would read "photonpano[kornia]" in an install hint as markup and drop it
        table.add_row(*(escape(str(v)) for v in (info.key, info.stage, info.module, info.distribution,
                                                 info.version, info.status)))
    Console(width=200).print(table)


@app.command()
@one_line_errors
def validate(spec: Annotated[Path, typer.Argument(help="Pipeline spec (YAML).")], set_: SetOption = None) -> None:
    """Validate a spec without reading any data."""
    from .spec import check_available, dump_spec, load_spec

    host = _host()
    parsed = load_spec(spec, host, set_ or [])
    check_available(parsed)
    for note in host.collisions:  # a third party offering a name or key already taken
        typer.secho(f"warning: {note}", fg=typer.colors.YELLOW, err=True)
    typer.echo(f"{spec}: valid")
    typer.echo(dump_spec(parsed))


@app.command()
@one_line_errors
def schema() -> None:
    """Print the JSON schema of pipeline specs (for editor completion of YAML specs)."""
    from .spec import spec_model

    typer.echo(json.dumps(spec_model(_host()).model_json_schema(), indent=2))


def main() -> None:
    """Entry point of the ``photonpano`` command."""
    import warnings

    # caveats of a capture (e.g. a truncated last file) print as one line
    warnings.showwarning = lambda message, *args, **kwargs: typer.secho(f"warning: {message}", err=True,
                                                                        fg=typer.colors.YELLOW)
    from .cli_io import GuardedStdout, silence_stdout, stdout_problem
    from .faults import interrupts_outside_compilers
    from .watchdog import command_line, exit_if_stuck

    sys.stdout = GuardedStdout(sys.stdout)
    command_line()
    code: int | str | None = 0
    try:
        with interrupts_outside_compilers():  # Ctrl-C while numba loads a kernel would be lost or crash on exit
            app()
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        code = 130
    except SystemExit as done:
        code = done.code
    except OSError:  # standard output full or closed while printing: one line, no traceback
        if sys.stdout.failure is None:
            raise
    problem = stdout_problem()  # a small output still sits in the buffer: flush it here, not at exit
    if problem is not None:
        if problem:
            typer.secho(f"error: {problem}", fg=typer.colors.RED, err=True)
        silence_stdout()
        code = 1
    elif code in (0, None) and _log_failed():
        code = 1
    exit_if_stuck(code if isinstance(code, int) else 1)  # a hung plugin's thread cannot be joined at exit
    sys.exit(code)


def _log_failed() -> bool:
    """Whether the ``--log-file`` handler failed during the command (its line is already printed)."""
    import logging

    from .cli_io import LogFileHandler

    return any(isinstance(h, LogFileHandler) and h.failure for h in logging.getLogger("photonpano").handlers)


from . import cli_tools  # noqa: E402, F401  (registers pose, convert, batch, compare, score and video on ``app``)

if __name__ == "__main__":  # pragma: no cover
    # ``python -m photonpano.cli``: this file runs as ``__main__``; its commands and cli_tools' are on the one
    # ``cli_base.app``
    main()
