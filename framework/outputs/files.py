"""Atomic files: written under a temporary name, synced, renamed into place; JSON helpers.

Every file is written under a temporary name in its folder (``.partial-<pid>-<name>``),
flushed to disk and renamed into place (``os.replace``), so a file under its final name
is always complete.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import OutputError

__all__ = ["atomic_path", "save_npy", "write_text", "json_default"]

PARTIAL = ".partial-"
"""Prefix of the temporary names of files being written."""


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system can sync a folder
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def oserror(path: Path, exc: OSError) -> OutputError:
    """Return the one-line :class:`~photonpano.errors.OutputError` for an OS error on ``path``."""
    return OutputError(f"cannot write {path}: {exc.strerror or type(exc).__name__}")


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is synced and renamed to ``path``.

    The temporary name keeps the suffix (writers such as ``cv2.imwrite`` choose the format
    from it). If the block raises, the temporary file is removed and ``path`` is untouched.

    Raises:
        OutputError: an OS error (read-only folder, full disk, a file as parent), as one
            line naming ``path``.
    """
    path = Path(path)
    tmp = path.with_name(f"{PARTIAL}{os.getpid()}-{path.name}")
    try:
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        raise oserror(path, exc) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def save_npy(path: Path, array: NDArray) -> None:
    """Write ``array`` to the ``.npy`` file ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.save(handle, array, allow_pickle=False)


def write_text(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def json_default(value: Any) -> Any:
    """``json.dumps`` fallback for numpy scalars and arrays and paths."""
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
