"""The output folder of one run: a lock, a manifest, atomic writes, cleanup, checkpoints."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from numpy.typing import NDArray

from ..errors import OutputError
from .checkpoint import CHECKPOINTS, Checkpoint
from .files import PARTIAL, atomic_path, oserror, save_npy, write_text

__all__ = ["MANIFEST", "LOCK", "RUN_JSON", "RunFolder"]

MANIFEST = "manifest.json"
"""The list of files a run wrote (JSON: ``{"files": [...], "complete": bool}``)."""
LOCK = ".photonpano.lock"
"""Held (created exclusively) while a run writes into the folder."""
RUN_JSON = "run.json"
"""Written last; its presence means the run is complete."""


class RunFolder:
    """The output folder of one run: lock, manifest, atomic writes, cleanup and checkpoints.

    Use as a context manager around the whole run; call :meth:`begin` once the spec is
    valid and the source is open, write with :meth:`save_npy`, :meth:`write_text` or
    :meth:`path` + :func:`atomic_path`, and finish with :meth:`commit`.

    Args:
        path: the output folder (created if missing).
        force: remove the previous run's outputs (its manifest files) and write anew.
        resume: continue the interrupted run in the folder from its last checkpoint.
        inputs: files and folders the run reads; none may lie inside ``path``.

    Raises:
        OutputError: from ``__enter__``: a file in place of the folder, an input inside
            it, a non-empty folder without ``force``/``resume``, another run holding the
            lock, nothing to resume, or an OS error (each one line naming the path).
    """

    def __init__(self, path: Path, *, force: bool = False, resume: bool = False,
                 inputs: Sequence[Path] = ()) -> None:
        self.root = Path(path)
        self.force, self.resume = force, resume
        self.inputs = [Path(p) for p in inputs]
        self.files: list[str] = []
        self._previous: list[str] = []
        self._created = False
        self._locked = False
        self._begun = False
        self._committed = False
        self._existing: set[str] = set()

    # -- opening ---------------------------------------------------------------------
    def __enter__(self) -> RunFolder:
        root = self.root
        if root.exists() and not root.is_dir():
            raise OutputError(f"output {root} exists and is not a folder")
        resolved = root.resolve()
        for item in self.inputs:
            item = item.resolve()
            if item == resolved or resolved in item.parents:
                raise OutputError(f"input {item} lies inside the output folder {root}; "
                                  "choose an output folder that holds no input")
        try:
            self._created = not root.exists()
            root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise oserror(root, exc) from None
        self._lock()
        try:
            self._inspect()
        except BaseException:
            self._unlock()
            if self._created:
                with contextlib.suppress(OSError):
                    root.rmdir()
            raise
        return self

    def _lock(self) -> None:
        lock = self.root / LOCK
        stamp = f"{os.getpid()} {socket.gethostname()}\n"
        for _ in range(2):
            try:
                fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                if _lock_is_stale(lock):
                    with contextlib.suppress(OSError):
                        lock.unlink()
                    continue
                holder = _read(lock).split()[:1] or ["?"]
                raise OutputError(f"output folder {self.root} is in use by another run (pid {holder[0]}, "
                                  f"lock {lock}); wait for it or choose another folder") from None
            except OSError as exc:
                raise oserror(lock, exc) from None
            with os.fdopen(fd, "w") as handle:
                handle.write(stamp)
            self._locked = True
            return
        raise OutputError(f"output folder {self.root}: cannot take the lock {lock}")

    def _unlock(self) -> None:
        if self._locked:
            with contextlib.suppress(OSError):
                (self.root / LOCK).unlink()
            self._locked = False

    def _inspect(self) -> None:
        present = {p.name for p in self.root.iterdir()} - {LOCK}
        manifest = _read_manifest(self.root / MANIFEST)
        if self.resume:
            if manifest is None:
                raise OutputError(f"--resume: {self.root} holds no interrupted run (no {MANIFEST})")
            if (self.root / RUN_JSON).exists():
                raise OutputError(f"--resume: the run in {self.root} is already complete ({RUN_JSON} exists)")
            self.files = list(manifest)
            self._existing = present
            return
        if present and not self.force:
            raise OutputError(f"output folder {self.root} is not empty; choose another, pass --force "
                              "(replaces the previous run's outputs) or --resume (continues an "
                              "interrupted run)")
        self._previous = list(manifest or [])
        self._existing = present - set(self._previous) - {MANIFEST}

    # -- writing ---------------------------------------------------------------------
    def begin(self) -> None:
        """Start writing: remove the previous run's outputs (``force``), write the manifest.

        Call once the spec is valid and the source is open. Idempotent.
        """
        if self._begun:
            return
        self._begun = True
        if self._previous:
            self._remove(self._previous + [MANIFEST])
            self._existing -= set(self._previous)
        self._remove_partials()
        self._write_manifest(complete=False)

    def path(self, name: str) -> Path:
        """Record ``name`` (relative, may contain ``/``) in the manifest and return its final path.

        Write the file through :func:`atomic_path`; parent folders are created.
        """
        self.begin()
        if name not in self.files:
            self.files.append(name)
            self._write_manifest(complete=False)
        target = self.root / name
        if target.parent != self.root:
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise oserror(target.parent, exc) from None
        return target

    def save_npy(self, name: str, array: NDArray) -> Path:
        """Write ``array`` as ``name`` atomically; returns its path."""
        path = self.path(name)
        save_npy(path, array)
        return path

    def write_text(self, name: str, text: str) -> Path:
        """Write ``text`` as ``name`` atomically; returns its path."""
        path = self.path(name)
        write_text(path, text)
        return path

    def write_with(self, name: str, writer: Callable[[Path], Any]) -> Path:
        """Call ``writer(tmp_path)`` and rename the result to ``name`` (e.g. a PNG or a plot)."""
        path = self.path(name)
        with atomic_path(path) as tmp:
            writer(tmp)
        return path

    def adopt_new_files(self) -> None:
        """Add files that appeared since the run began (written by observer plugins) to the manifest."""
        new = self._new_files()
        if new:
            self.files.extend(new)
            self._write_manifest(complete=False)

    def _new_files(self) -> list[str]:
        known = set(self.files) | self._existing | {MANIFEST, LOCK}
        names = [p.relative_to(self.root).as_posix() for p in sorted(self.root.rglob("*")) if p.is_file()]
        return [n for n in names if n not in known and n.split("/")[0] not in self._existing
                and not Path(n).name.startswith(PARTIAL)]

    # -- checkpoints -----------------------------------------------------------------
    def save_checkpoint(self, checkpoint: Checkpoint) -> None:
        """Write ``checkpoints/level_<k>.npz`` (and drop the older ones)."""
        checkpoint.save(self.path(f"{CHECKPOINTS}/level_{checkpoint.level}.npz"))
        for older in range(1, checkpoint.level):
            with contextlib.suppress(OSError):
                (self.root / CHECKPOINTS / f"level_{older}.npz").unlink()

    def last_checkpoint(self) -> Checkpoint | None:
        """Return the latest complete checkpoint in the folder, or None."""
        found = sorted(((int(p.stem.split("_")[1]), p) for p in (self.root / CHECKPOINTS).glob("level_*.npz")
                        if p.stem.split("_")[1].isdigit()), reverse=True)
        return Checkpoint.load(found[0][1]) if found else None

    # -- finishing -------------------------------------------------------------------
    def commit(self, summary_text: str) -> None:
        """Record every output, write ``run.json`` last, then drop the checkpoints."""
        self.adopt_new_files()
        if RUN_JSON not in self.files:
            self.files.append(RUN_JSON)
        self._write_manifest(complete=True)
        write_text(self.root / RUN_JSON, summary_text)
        self._committed = True
        shutil.rmtree(self.root / CHECKPOINTS, ignore_errors=True)
        self.files = [n for n in self.files if not n.startswith(f"{CHECKPOINTS}/")]
        self._write_manifest(complete=True)

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        try:
            if kind is not None and not self._committed:
                self._abandon(keep_checkpoints=issubclass(kind, KeyboardInterrupt))
        finally:
            self._unlock()

    def _abandon(self, keep_checkpoints: bool) -> None:
        """After a failure: remove this run's files (an interrupted run keeps its checkpoints)."""
        if self._begun:
            self.files.extend(self._new_files())
        self._remove_partials()
        if keep_checkpoints and any((self.root / CHECKPOINTS).glob("level_*.npz")):
            keep = [n for n in self.files if n.startswith(f"{CHECKPOINTS}/") or n == "spec.yaml"]
            self._remove([n for n in self.files if n not in keep])
            self.files = keep
            with contextlib.suppress(OutputError):
                self._write_manifest(complete=False)
            return
        if self._begun:
            self._remove(self.files + [MANIFEST])
        if self._created:
            with contextlib.suppress(OSError):
                if not [p for p in self.root.iterdir() if p.name != LOCK]:
                    self._unlock()
                    self.root.rmdir()

    def _remove(self, names: Sequence[str]) -> None:
        for name in names:
            target = self.root / name
            with contextlib.suppress(FileNotFoundError, NotADirectoryError):
                if target.is_dir() and not target.is_symlink():
                    continue
                target.unlink()
        for folder in sorted({(self.root / n).parent for n in names}, key=lambda p: -len(p.parts)):
            while folder != self.root and folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
                folder = folder.parent

    def _remove_partials(self) -> None:
        for leftover in self.root.rglob(f"{PARTIAL}*"):
            with contextlib.suppress(OSError):
                leftover.unlink()

    def _write_manifest(self, complete: bool) -> None:
        write_text(self.root / MANIFEST, json.dumps({"files": self.files, "complete": complete}, indent=1))


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def _read_manifest(path: Path) -> list[str] | None:
    """Return the file names of a manifest (None without one; a damaged one lists nothing)."""
    if not path.is_file():
        return None
    try:
        data = json.loads(_read(path))
        files = data.get("files", []) if isinstance(data, dict) else []
    except ValueError:
        return []
    return [f for f in files
            if isinstance(f, str) and ".." not in Path(f).parts and not Path(f).is_absolute()]


def _lock_is_stale(lock: Path) -> bool:
    """A lock is stale when its process (on this host) no longer runs."""
    fields = _read(lock).split()
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
    return _is_zombie(pid)


def _is_zombie(pid: int) -> bool:
    with contextlib.suppress(OSError, IndexError):
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    return False

