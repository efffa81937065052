"""What a run folder's bookkeeping reads from disk: its manifest, the files below it, its lock.

Reading only, and lenient: a damaged manifest lists nothing, an unreadable file reads
as ''. Writing is :class:`~photonpano.outputs.RunFolder`'s.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from pathlib import Path

__all__ = ["read_text_lenient", "read_manifest", "walk_files", "lock_is_stale", "is_zombie"]


def read_text_lenient(path: Path) -> str:
    """The text of ``path`` (undecodable bytes replaced), or '' if it cannot be read."""
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def read_manifest(path: Path) -> tuple[list[str] | None, dict[str, str] | None]:
    """Return the file names and sha256 hashes of a manifest.

    Returns ``(None, None)`` without a manifest (or a manifest that is a link); a
    damaged one lists nothing. Hashes are None for a manifest that records none (written
    before hashes were recorded): its files then get the path checks only.
    """
    if path.is_symlink() or not path.is_file():
        return None, None
    try:
        data = json.loads(read_text_lenient(path))
    except ValueError:
        return [], {}
    if not isinstance(data, dict):
        return [], {}
    files = data.get("files", [])
    files = [f for f in files if isinstance(f, str) and f and ".." not in Path(f).parts
             and not Path(f).is_absolute()] if isinstance(files, list) else []
    hashes = data.get("sha256")
    if hashes is None:
        return files, None
    if not isinstance(hashes, dict):
        return files, {}
    return files, {k: v for k, v in hashes.items() if isinstance(k, str) and isinstance(v, str)}


def walk_files(root: Path, links: bool = False) -> list[str]:
    """Names (relative, ``/``-separated, sorted) of the regular files below ``root``, never following a link.

    With ``links``, symbolic links (to anything) are listed too.
    """
    names = []
    for folder, dirs, files in os.walk(root, followlinks=False):
        base = Path(folder)
        entries = files + [d for d in dirs if (base / d).is_symlink()] if links else files
        for entry in entries:
            path = base / entry
            if path.is_symlink() and not links:
                continue
            if links or path.is_file():
                names.append(path.relative_to(root).as_posix())
    return sorted(names)


def lock_is_stale(lock: Path) -> bool:
    """A lock is stale when its process (on this host) no longer runs."""
    fields = read_text_lenient(lock).split()
    if len(fields) < 2 or not fields[0].isdigit():
        return True
    if fields[1] != socket.gethostname():
        return False
    pid = int(fields[0])
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return is_zombie(pid)


def is_zombie(pid: int) -> bool:
    """Whether process ``pid`` has exited and waits for its parent (Linux ``/proc``; False where unknown)."""
    with contextlib.suppress(OSError, IndexError):
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    return False

