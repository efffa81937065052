"""The command line's own streams: the ``--log-file`` handler and standard output, on a full disk.

A log file or standard output that cannot be written (``--log-file /dev/full``,
``photonpano plugins > /dev/full``, a disk filling up during a run) ends the command
with one line naming the path and exit status 1, never a traceback or logging's
"--- Logging error ---" dump.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

from .errors import OutputError

__all__ = ["LogFileHandler", "open_log_file", "GuardedStdout", "stdout_name", "stdout_problem",
           "silence_stdout"]


class LogFileHandler(logging.FileHandler):
    """A ``FileHandler`` that, when a write fails, reports it once on stderr and stops.

    Attributes:
        failure: the one-line message of the first failed write, or None.
    """

    def __init__(self, path: Path) -> None:
        super().__init__(path, encoding="utf-8")
        self.path = Path(path)
        self.failure: str | None = None

    def emit(self, record: logging.LogRecord) -> None:
        """Write ``record`` unless an earlier write failed."""
        if self.failure is None:
            super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 (logging's name)
        """Replace logging's traceback dump with one line; later records are dropped."""
        exc = sys.exc_info()[1]
        if self.failure is not None:
            return
        reason = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        self.failure = f"--log-file {self.path}: cannot write ({reason}); logging to it stopped"
        with _suppress():
            sys.stderr.write(f"error: {self.failure}\n")
            sys.stderr.flush()


class _suppress:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> bool:
        return True


def open_log_file(path: Path, header: str) -> LogFileHandler:
    """Open ``path`` for appending and write ``header`` (one line) to it at once.

    Writing and flushing the header at start finds a full disk, ``/dev/full`` or a
    read-only file before any work.

    Args:
        path: the log file (created if missing).
        header: the first line (without newline), e.g. the version and command line.

    Raises:
        OutputError: the file cannot be opened or written; one line naming it.
    """
    try:
        handler = LogFileHandler(path)
    except OSError as exc:
        raise OutputError(f"--log-file {path}: cannot open it ({exc.strerror or exc})") from None
    stream = handler.stream
    assert stream is not None  # FileHandler opens its file at construction (delay=False)
    try:
        stream.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {header}\n")
        stream.flush()
    except OSError as exc:
        with _suppress():
            stream.close()  # the unwritten buffer is dropped with the error
        raise OutputError(f"--log-file {path}: cannot write ({exc.strerror or exc})") from None
    return handler


class GuardedStdout:
    """Standard output, wrapped: a failed write or flush is remembered (and raised as usual).

    :func:`photonpano.cli.main` installs it as ``sys.stdout`` so that, when a command
    dies of an ``OSError``, it can tell a full or closed standard output from anything
    else. Every other attribute is the wrapped stream's.

    Attributes:
        failure: the first ``OSError`` of a write or flush, or None.
    """

    def __init__(self, stream) -> None:
        self._stream = stream
        self.failure: OSError | None = None

    def write(self, text: str) -> int:
        """Write ``text`` to the wrapped stream (an ``OSError`` is remembered, then raised)."""
        try:
            return self._stream.write(text)
        except OSError as exc:
            self.failure = self.failure or exc
            raise

    def flush(self) -> None:
        """Flush the wrapped stream (an ``OSError`` is remembered, then raised)."""
        try:
            self._stream.flush()
        except OSError as exc:
            self.failure = self.failure or exc
            raise

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def stdout_name() -> str:
    """Where standard output goes, for messages: ``standard output (/dev/full)`` where it can be told."""
    with _suppress():
        if sys.__stdout__ is not None:  # None: Python runs without standard output
            return f"standard output ({os.readlink(f'/proc/self/fd/{sys.__stdout__.fileno()}')})"
    return "standard output"


def stdout_problem() -> str | None:
    """Flush standard output; return a one-line error naming it if this or an earlier write failed.

    A closed pipe (``photonpano plugins | head``) is not an error worth a line: it
    returns ``""`` (the caller exits 1 quietly, as click does).
    """
    import errno

    failure = getattr(sys.stdout, "failure", None)
    try:
        sys.stdout.flush()
    except (OSError, ValueError) as exc:
        failure = failure or exc
    if failure is None:
        return None
    if getattr(failure, "errno", None) == errno.EPIPE:
        return ""
    return f"cannot write to {stdout_name()}: {getattr(failure, 'strerror', None) or failure}"


def silence_stdout() -> None:
    """Point standard output at the null device, so interpreter exit cannot fail on it again."""
    with _suppress():
        if sys.__stdout__ is None:  # Python runs without standard output: nothing to silence
            return
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.__stdout__.fileno())
        os.close(devnull)
