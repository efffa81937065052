"""Atomic files: written under a temporary name, synced, renamed into place; JSON helpers.

Every file is written under a temporary name in its folder (``.partial-<pid>-<name>``),
flushed to disk and renamed into place (``os.replace``), so a file under its final name
is always complete.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import shutil
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import OutputError

__all__ = ["atomic_path", "save_npy", "write_text", "json_default", "inside", "refuse_symlink", "sha256_file",
           "regular_file_inside"]

PARTIAL = ".partial-"
"""Prefix of the temporary names of files being written."""


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system can sync a folder
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def oserror(path: Path, exc: OSError, needed: int | None = None) -> OutputError:
    """Return the one-line :class:`~photonpano.errors.OutputError` for an OS error on ``path``.

    A full disk (``ENOSPC``, ``EDQUOT``) also states the free space left on ``path``'s
    file system and, if given, the ``needed`` bytes.
    """
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        free = _free_bytes(Path(path))
        if free is not None:
            reason += f" ({_mib(free)} free there"
            reason += f", {_mib(needed)} needed)" if needed else ")"
    return OutputError(f"cannot write {path}: {reason}")


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def _free_bytes(path: Path) -> int | None:
    for folder in (path, *path.parents):
        with contextlib.suppress(OSError):
            if folder.is_dir():
                return shutil.disk_usage(folder).free
    return None


def refuse_symlink(path: Path, what: str) -> None:
    """Refuse ``path`` if it is a symbolic link (dangling or not): writers never write through one.

    Args:
        path: a file or folder about to be written or created.
        what: how the message names it (e.g. ``"output"``, ``"convert: temporary file"``).

    Raises:
        OutputError: one line naming ``path`` and where the link points.
    """
    path = Path(path)
    if path.is_symlink():
        try:
            target = os.readlink(path)
        except OSError:
            target = "?"
        raise OutputError(f"{what} {path} is a symbolic link (to {target}); refusing to write through it, "
                          "give a real path")


def inside(root: Path, name: str, folder: bool = False) -> Path:
    """Return ``root / name`` after checking that it cannot lead out of ``root``.

    ``name`` is relative (``/`` separated, no ``..``); no existing folder component
    below ``root`` may be a symbolic link, and the parent must resolve inside ``root``.
    Writers call this before writing ``name``, so a link planted in an output folder
    (``link -> /elsewhere``) is never followed. The file itself may be a link: the
    atomic rename of :func:`atomic_path` replaces the link, never its target; with
    ``folder`` (a folder to write into) it may not be a link either.

    Raises:
        OutputError: an absolute name, ``..``, a symbolic link or a non-folder component;
            one line naming the path.
    """
    root = Path(root)
    parts = Path(name).parts
    if not parts or Path(name).is_absolute() or ".." in parts:
        raise OutputError(f"output name {name!r} in {root} is not a relative path inside the folder")
    current = root
    for i, part in enumerate(parts):
        current = current / part
        try:
            mode = os.lstat(current).st_mode
        except FileNotFoundError:
            break
        except OSError as exc:
            raise oserror(current, exc) from None
        if i == len(parts) - 1 and not folder:
            break
        if stat.S_ISLNK(mode):
            refuse_symlink(current, "output")
        if not stat.S_ISDIR(mode):
            raise OutputError(f"cannot write {root / name}: {current} is not a folder")
    target = root / name
    resolved_root = root.resolve()
    if target.parent.resolve() != resolved_root and resolved_root not in target.parent.resolve().parents:
        raise OutputError(f"output {target} resolves outside the output folder {root}")
    return target


def regular_file_inside(root: Path, name: str) -> Path | None:
    """Return ``root / name`` if it is a regular file reached without any symbolic link, else None.

    The checks of :func:`inside` (no link, no ``..``, resolved inside ``root``) plus: the
    path exists and is a regular file (not a folder, device, socket or link). Never raises.
    """
    try:
        target = inside(root, name)
        return target if stat.S_ISREG(os.lstat(target).st_mode) else None  # lstat: a link is not regular
    except (OutputError, OSError):
        return None


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file's bytes (read in 1 MiB blocks, without following a final link).

    Raises:
        OSError: the file cannot be read (or is a symbolic link: ``ELOOP``).
    """
    digest = hashlib.sha256()
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    with os.fdopen(fd, "rb") as handle:
        for block in iter(lambda: handle.read(2**20), b""):
            digest.update(block)
    return digest.hexdigest()


@contextlib.contextmanager
def atomic_path(path: Path, before_rename: Callable[[Path], Any] | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is synced and renamed to ``path``.

    The temporary name keeps the suffix (writers such as ``cv2.imwrite`` choose the format
    from it). If the block raises, the temporary file is removed and ``path`` is untouched.
    ``before_rename(tmp)``, if given, is called once the file is complete and synced,
    before the rename (e.g. to record its hash). A link planted under the temporary name
    is removed first, never written through; the rename replaces a link at ``path``
    itself, never its target.

    Raises:
        OutputError: an OS error (read-only folder, full disk, a file as parent), as one
            line naming ``path``.
    """
    path = Path(path)
    tmp = path.with_name(f"{PARTIAL}{os.getpid()}-{path.name}")
    with contextlib.suppress(OSError):
        if tmp.is_symlink():  # planted under our temporary name: never write through it
            tmp.unlink()
    try:
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        if before_rename is not None:
            before_rename(tmp)
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
