"""COLMAP's log routed to Python logging (pycolmap writes some lines to stderr whatever its log level)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def colmap_log(name: str = "photonpano.colmap") -> Iterator[None]:
    """Route COLMAP's log lines (glog, written to file descriptor 2) to the Python logger ``name``.

    COLMAP writes some lines (bundle adjustment headings, timers, errors) to stderr
    whatever pycolmap's ``logging.minloglevel`` says. Inside the block, file descriptor 2
    goes to a temporary file while ``sys.stderr`` (if it was file descriptor 2) keeps
    writing to the terminal, so progress bars still draw. On exit every glog line
    (severity letter, date, time, thread, ``file:line]``) is logged at DEBUG (``I``,
    ``W``) or INFO (``E``, ``F``: COLMAP's own errors, which the estimator handles; what
    the run cannot recover from is raised as a ``StageError``), so the command line shows
    COLMAP's lines only with ``-v`` and ``--log-file`` keeps them. COLMAP makes its INFO
    and WARNING lines only when a handler of the logger shows DEBUG records
    (``minloglevel`` 0, else 2). Anything else written to descriptor 2 meanwhile is
    written back to stderr unchanged.

    Args:
        name: the logger.
    """
    import logging
    import re
    import sys
    import tempfile

    ansi = re.compile(rb"\x1b\[[0-9;]*m")
    glog = re.compile(rb"^([IWEF])\d{8} [0-9:.]+ +\d+ ([^\]]+)\] ?(.*)$")
    severity = {b"I": logging.DEBUG, b"W": logging.DEBUG, b"E": logging.INFO, b"F": logging.INFO}
    logger = logging.getLogger(name)
    pycolmap: Any
    try:
        import pycolmap
    except ImportError:
        pycolmap = None
    level = getattr(getattr(pycolmap, "logging", None), "minloglevel", None)
    if level is not None:  # COLMAP's INFO and WARNING lines are made only when a handler would show them
        handlers = [h for item in (logger, *_parents(logger)) for h in item.handlers]
        pycolmap.logging.minloglevel = 0 if any(h.level <= logging.DEBUG for h in handlers) else 2
    previous = sys.stderr
    try:
        swap = previous is not None and previous.fileno() == 2
    except (AttributeError, OSError, ValueError):  # a replaced stderr (pytest's capture, a notebook)
        swap = False
    if previous is not None:
        previous.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as capture:
        terminal = open(saved, "w", buffering=1, closefd=False, errors="replace",
                        encoding=getattr(previous, "encoding", None) or "utf-8")
        os.dup2(capture.fileno(), 2)
        if swap:
            sys.stderr = terminal
        try:
            yield
        finally:
            if swap:
                sys.stderr = previous
            if level is not None:
                pycolmap.logging.minloglevel = level
            terminal.flush()
            os.dup2(saved, 2)
            terminal.close()
            os.close(saved)
            capture.seek(0)
            other = []
            for line in capture.read().splitlines(keepends=True):
                clean = ansi.sub(b"", line).rstrip(b"\r\n")
                match = glog.match(clean)
                if match:
                    logger.log(severity[match.group(1)], "COLMAP %s: %s", match.group(2).decode(errors="replace"),
                               match.group(3).decode(errors="replace"))
                elif clean.strip():
                    other.append(line)
            if other:
                os.write(2, b"".join(other))


def _parents(logger: Any) -> list[Any]:
    """The loggers whose handlers a record of ``logger`` reaches (its ancestors while it propagates)."""
    found = []
    while logger.propagate and logger.parent is not None:
        logger = logger.parent
        found.append(logger)
    return found
