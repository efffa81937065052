"""The ``photonpano`` command line.

``run`` a spec, ``pano`` an input with the paper's default spec, ``demo`` on the bundled
photograph, list ``plugins``, ``validate`` a spec and print its JSON ``schema``; the
commands beside the main job (``pose``, ``convert``, ``compare``, ``video``) are in
:mod:`photonpano.cli_tools`.
Expected failures (bad input, bad spec, broken plugin) print one line and exit 1.
"""

from __future__ import annotations

import functools
import json
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Callable, Optional

import typer

from . import __version__
from .errors import PhotonpanoError

app = typer.Typer(add_completion=True, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Motion estimation and panoramas from single-photon cameras "
                       "(stratified temporal re-sampling, Jungerman et al., ICCV 2023).")

SetOption = Annotated[Optional[list[str]], typer.Option(
    "--set", "-s", help="Override a spec field: stage.field=value (value parsed as YAML). Repeatable.")]
OutOption = Annotated[Path, typer.Option("--output", "-o", help="Output folder (must be empty unless --force).")]
ForceOption = Annotated[bool, typer.Option("--force", help="Replace the previous run's outputs in the output "
                                           "folder (the files its manifest lists; other files are kept).")]
ResumeOption = Annotated[bool, typer.Option("--resume", help="Continue the interrupted run in the output "
                                            "folder from its last finished level (same spec).")]


_state: dict[str, Any] = {"debug": False, "quiet": False}
"""Global options of the command line (set by :func:`_global_options`)."""


def _version(value: bool) -> None:
    if value:
        typer.echo(f"photonpano {__version__}")
        raise typer.Exit()


@app.callback()
def _global_options(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Print debug messages.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print only warnings, errors and the result; "
                                                             "no progress bars.")] = False,
    log_file: Annotated[Optional[Path], typer.Option(
        "--log-file", help="Append a detailed log (debug level, with timestamps, tracebacks of plugin "
                           "failures) to this file.")] = None,
    debug: Annotated[bool, typer.Option(
        "--debug", help="Show the full traceback of unexpected errors (plugin bugs) instead of one line.")] = False,
) -> None:
    """Motion estimation and panoramas from single-photon cameras."""
    import logging

    _state.update(quiet=quiet, debug=debug)
    logger = logging.getLogger("photonpano")
    logger.setLevel(logging.DEBUG)
    for handler in list(logger.handlers):  # one set of handlers per invocation (tests call main repeatedly)
        if getattr(handler, "_photonpano_cli", False):
            logger.removeHandler(handler)
            handler.close()
    console = logging.StreamHandler(sys.stderr)
    # the progress display already prints each level's line: the console log adds only
    # warnings, or everything with --verbose
    console.setLevel(logging.DEBUG if verbose else logging.WARNING)
    console.setFormatter(logging.Formatter("%(message)s"))
    handlers: list[logging.Handler] = [console]
    if log_file is not None:
        from .cli_io import open_log_file

        try:  # a full disk or /dev/full fails here, in one line, before any work
            file_handler = open_log_file(log_file, f"photonpano {__version__}: {' '.join(sys.argv[1:])}")
        except PhotonpanoError as exc:
            _fail(str(exc))
        file_handler.setLevel(logging.DEBUG)
        file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        handlers.append(file_handler)
    for handler in handlers:
        handler._photonpano_cli = True  # type: ignore[attr-defined]
        logger.addHandler(handler)
    logger.propagate = False


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(1)


def one_line_errors(command: Callable[..., Any]) -> Callable[..., Any]:
    """Make a command print an expected failure (:class:`PhotonpanoError`) as one line and exit 1."""
    @functools.wraps(command)
    def run_command(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except PhotonpanoError as exc:
            _fail(str(exc))
    return run_command


def _host():
    from .host import PluginHost

    return PluginHost()


@contextmanager
def _observed(host):
    """Register the log observer and, unless ``--quiet``, progress bars on ``host`` for a block."""
    from .progress import LogObserver, RichProgress, reporting

    observers = {"cli-log": LogObserver()}
    bars = None
    if not _state["quiet"]:
        from rich.console import Console

        bars = observers["cli-progress"] = RichProgress(Console(stderr=True))
    for name, observer in observers.items():
        host.register(observer, name=name)
    try:
        with reporting(host):
            yield
    finally:
        if bars is not None:
            bars.stop()
        for name in observers:
            host.unregister(name)


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

        execute_pose(parsed, output, force, host)
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


def _passes_through(exc: BaseException) -> bool:
    """Whether an exception from plugin code propagates as it is rather than as one line naming the plugin.

    Expected failures (:class:`PhotonpanoError`, already one line), Ctrl-C, ``sys.exit``
    and generator shutdown do, and everything with ``--debug``; any other exception,
    a ``BaseException`` subclass that is not an ``Exception`` included, is a plugin's bug.
    """
    return _state["debug"] or isinstance(exc, (PhotonpanoError, KeyboardInterrupt, SystemExit, GeneratorExit))


def _plugin_failure(exc: BaseException, host, spec=None):
    """One-line :class:`PluginError` for a plugin's bug; the traceback goes to the log (file)."""
    import logging

    from .faults import plugin_failure

    logging.getLogger("photonpano").debug("unexpected exception in plugin code", exc_info=exc)
    return plugin_failure(exc, host, spec)


def _capture_spec(path: Path, host) -> dict[str, Any]:
    """:func:`photonpano.presets.spec_for_capture`, with a plugin's bug reported as one line."""
    from .presets import spec_for_capture

    try:
        return spec_for_capture(path, host)
    except BaseException as exc:  # a plugin's bug: one line naming it
        if _passes_through(exc):
            raise
        raise _plugin_failure(exc, host) from exc


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
    typer.echo(f"simulating {parsed.source.frames} binary frames of {parsed.source.height}x"
               f"{parsed.source.width} at flux {parsed.source.flux} from the bundled photo ...")
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

    sys.stdout = GuardedStdout(sys.stdout)
    code: int | str | None = 0
    try:
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
    sys.exit(code)


def _log_failed() -> bool:
    """Whether the ``--log-file`` handler failed during the command (its line is already printed)."""
    import logging

    from .cli_io import LogFileHandler

    return any(isinstance(h, LogFileHandler) and h.failure for h in logging.getLogger("photonpano").handlers)


from . import cli_tools  # noqa: E402, F401  (registers pose, convert, batch, compare, score and video on ``app``)

if __name__ == "__main__":  # pragma: no cover
    # ``python -m photonpano.cli``: run the imported module's app, on which cli_tools registered its commands
    # (this file runs as ``__main__``, a second module whose app lacks them)
    from photonpano.cli import main as _main

    _main()
