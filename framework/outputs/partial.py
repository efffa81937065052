"""The ``<output>.part`` of a conversion: claimed exclusively, owned, restarted only when it is provably ours.

A converter (``photonpano convert``) writes into ``<output>.part`` and renames it to
``output`` when complete, so a killed conversion never leaves a complete-looking
``output``. Before it creates the ``.part`` it creates ``<output>.part.owner``
exclusively, holding ``<pid> <host>``; both are removed when the conversion ends. A
``.part`` without that record was not written by a conversion and is never written
through nor removed. A conversion killed before it finished leaves both; ``restart``
(``photonpano convert --resume``) removes them, if the owner process no longer runs,
and the conversion starts again from the beginning (its output is then byte-identical
to that of an uninterrupted conversion).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import socket
import stat
from pathlib import Path

from ..errors import OutputError
from .disk import lock_is_stale, read_text_lenient
from .files import oserror

__all__ = ["claim_partial", "release_partial", "OWNER_SUFFIX"]

OWNER_SUFFIX = ".part.owner"
"""Suffix of the record ``<output>.part.owner`` (``<pid> <host>``) of the conversion writing ``<output>.part``."""

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _names(output: Path) -> tuple[Path, Path]:
    output = Path(output)
    return output.with_name(output.name + ".part"), output.with_name(output.name + OWNER_SUFFIX)


def _kind(path: Path) -> str:
    return "a symbolic link" if path.is_symlink() else "a folder" if path.is_dir() else "a file"


def claim_partial(output: Path, restart: bool = False) -> Path:
    """Create ``<output>.part`` exclusively (an empty file, never through a link), owned by this process.

    Converters write into it (a folder writer removes the file and makes a folder of the
    same name), rename it to ``output`` when complete and then call
    :func:`release_partial`.

    Args:
        output: the file or folder the conversion will produce.
        restart: first remove the ``.part`` and owner record left by an interrupted
            conversion (its process no longer runs on this host); a ``.part`` with no
            owner record, a link, or one whose owner still runs is refused all the same.

    Returns:
        The path ``<output>.part`` (an empty regular file).

    Raises:
        OutputError: ``<output>.part`` or its owner record already exists (a file, a
            folder or a symbolic link: not this conversion's, or an interrupted one's
            without ``restart``), another conversion holds it, or it cannot be created;
            one line naming the path.
    """
    partial, owner = _names(output)
    if restart:
        _remove_interrupted(partial, owner)
    try:
        fd = os.open(owner, os.O_CREAT | os.O_EXCL | os.O_WRONLY | _NOFOLLOW, 0o644)
    except OSError as exc:
        if exc.errno not in (errno.EEXIST, errno.ELOOP):
            raise oserror(owner, exc) from None
        regular = stat.S_ISREG(os.lstat(owner).st_mode)
        if regular and lock_is_stale(owner):
            pid = (read_text_lenient(owner).split() or ["?"])[0]
            raise OutputError(f"convert: {partial} was left by an interrupted conversion (pid {pid}); rerun with "
                              "--resume to start it again, or remove it") from None
        if regular:
            raise OutputError(f"convert: {partial} is being written by another conversion (pid "
                              f"{(read_text_lenient(owner).split() or ['?'])[0]}, {owner}); wait for it") from None
        raise OutputError(f"convert: {owner} already exists ({_kind(owner)}, not written by this conversion); "
                          "remove it or choose another output") from None
    try:
        os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
    except OSError as exc:  # a full disk
        with contextlib.suppress(OSError):
            owner.unlink()
        raise oserror(owner, exc) from None
    finally:
        os.close(fd)
    try:
        fd = os.open(partial, os.O_CREAT | os.O_EXCL | os.O_WRONLY | _NOFOLLOW, 0o644)
    except OSError as exc:
        with contextlib.suppress(OSError):
            owner.unlink()
        if exc.errno in (errno.EEXIST, errno.ELOOP):
            raise OutputError(f"convert: {partial} already exists ({_kind(partial)}, not written by this "
                              "conversion); remove it or choose another output") from None
        raise oserror(partial, exc) from None
    os.close(fd)
    return partial


def release_partial(output: Path) -> None:
    """Remove this conversion's owner record of ``<output>.part`` (call once the ``.part`` is renamed or removed)."""
    _, owner = _names(output)
    with contextlib.suppress(OSError):
        if stat.S_ISREG(os.lstat(owner).st_mode) and read_text_lenient(owner).split()[:1] == [str(os.getpid())]:
            owner.unlink()


def _remove_interrupted(partial: Path, owner: Path) -> None:
    """Remove the ``.part`` (file or folder, never a link's target) and owner record of a dead conversion."""
    try:
        mode = os.lstat(owner).st_mode
    except FileNotFoundError:
        return  # nothing interrupted here (a lone .part is refused by the claim)
    except OSError as exc:
        raise oserror(owner, exc) from None
    if not stat.S_ISREG(mode):
        raise OutputError(f"convert: {owner} is {_kind(owner)}, not written by a conversion; remove it or "
                          "choose another output")
    if not lock_is_stale(owner):
        raise OutputError(f"convert: {partial} is being written by another conversion (pid "
                          f"{(read_text_lenient(owner).split() or ['?'])[0]}, {owner}); wait for it")
    try:
        mode = os.lstat(partial).st_mode if os.path.lexists(partial) else None
        if mode is not None and stat.S_ISDIR(mode):
            shutil.rmtree(partial)  # removes links inside it, never their targets
        elif mode is not None and stat.S_ISREG(mode):
            partial.unlink()
        elif mode is not None:
            raise OutputError(f"convert: {partial} is {_kind(partial)}, not written by a conversion; remove it "
                              "or choose another output")
        owner.unlink()
    except OSError as exc:
        raise oserror(partial, exc) from None
