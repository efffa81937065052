"""The ``photonpano`` application, its global options and the helpers its commands share.

:mod:`photonpano.cli` (the main commands) and :mod:`photonpano.cli_tools` (the commands
beside the main job) register their commands on :data:`app`; both import this module and
neither imports the other at import time (``cli`` imports ``cli_tools`` to register it).
"""

from __future__ import annotations

import functools
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Callable, Optional

import typer

from . import __version__
from .errors import PhotonpanoError

__all__ = ["app", "SetOption", "OutOption", "ForceOption", "ResumeOption", "one_line_errors"]

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
    """Register the log observer and, unless ``--quiet``, progress bars on ``host`` for a block.

    Yields the :class:`~photonpano.progress.RichProgress` (None with ``--quiet``): lines a
    command prints while bars are drawn go through its console, above the bars.
    """
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
            yield bars
    finally:
        if bars is not None:
            bars.stop()
        for name in observers:
            host.unregister(name)


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
