"""The output folder of one run: a lock, a manifest, atomic writes, cleanup, checkpoints."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import socket
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import OutputError
from ..watchdog import PluginHung
from .checkpoint import CHECKPOINTS, Checkpoint
from .disk import lock_is_stale, read_manifest, read_text_lenient, walk_files
from .files import PARTIAL, atomic_path, inside, oserror, refuse_symlink, regular_file_inside, sha256_file, write_text

__all__ = ["MANIFEST", "LOCK", "RUN_JSON", "RunFolder"]

MANIFEST = "manifest.json"
"""The list of files a run wrote (JSON: ``{"files": [...], "sha256": {name: hex}, "complete": bool}``)."""
LOCK = ".photonpano.lock"
"""Held (created exclusively) while a run writes into the folder."""
RUN_JSON = "run.json"
"""Written last; its presence means the run is complete."""


class RunFolder:
    """The output folder of one run: lock, manifest, atomic writes, cleanup and checkpoints.

    Use as a context manager around the whole run; call :meth:`begin` once the spec is
    valid and the source is open, write with :meth:`save_npy`, :meth:`write_text` or
    :meth:`path` + :func:`atomic_path`, and finish with :meth:`commit`.

    Nothing outside the folder is ever written or removed: the folder itself and every
    component of an output name must not be a symbolic link, and ``--force`` (or a failed
    run's cleanup) deletes a file the manifest names only if it is a regular file inside
    the folder, reached without a link, whose sha256 is the one the manifest recorded
    when the run wrote it (a manifest without hashes, from before they were recorded,
    gets the path checks only). Files that fail a check are kept.

    Args:
        path: the output folder (created if missing).
        force: remove the previous run's outputs (its manifest files) and write anew.
        resume: continue the interrupted run in the folder from its last checkpoint.
        inputs: files and folders the run reads; none may lie inside ``path``.
        final: the file written last by :meth:`commit`, whose presence means the run
            is complete (``run.json``; ``compare.json`` for ``photonpano compare``).

    Raises:
        OutputError: from ``__enter__``: a file in place of the folder, an input inside
            it, a non-empty folder without ``force``/``resume``, another run holding the
            lock, nothing to resume, or an OS error (each one line naming the path).
    """

    def __init__(self, path: Path, *, force: bool = False, resume: bool = False,
                 inputs: Sequence[Path] = (), final: str = RUN_JSON) -> None:
        self.root = Path(path)
        self.final = final
        self.force, self.resume = force, resume
        self.inputs = [Path(p) for p in inputs]
        self.files: list[str] = []
        self.hashes: dict[str, str] = {}
        self._previous: list[str] = []
        self._previous_hashes: dict[str, str] | None = None
        self._created = False
        self._locked = False
        self._begun = False
        self._committed = False
        self._existing: set[str] = set()

    # -- opening ---------------------------------------------------------------------
    def __enter__(self) -> RunFolder:
        root = self.root
        refuse_symlink(root, "output folder")
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
                if lock_is_stale(lock):
                    with contextlib.suppress(OSError):
                        lock.unlink()
                    continue
                holder = read_text_lenient(lock).split()[:1] or ["?"]
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
        manifest, hashes = read_manifest(self.root / MANIFEST)
        if self.resume:
            if manifest is None:
                raise OutputError(f"--resume: {self.root} holds no interrupted run (no {MANIFEST})")
            if (self.root / self.final).exists():
                raise OutputError(f"--resume: the run in {self.root} is already complete ({self.final} exists)")
            self.files = list(manifest)
            self.hashes = dict(hashes or {})
            self._existing = present
            return
        if present and not self.force:
            raise OutputError(f"output folder {self.root} is not empty; choose another, pass --force "
                              "(replaces the previous run's outputs) or --resume (continues an "
                              "interrupted run)")
        self._previous = list(manifest or [])
        self._previous_hashes = hashes
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
            kept = self._remove(self._previous, self._previous_hashes)
            self._remove([MANIFEST], None)
            self._existing -= set(self._previous) - {n.split("/")[0] for n in kept}
            self._existing = {n for n in self._existing if os.path.lexists(self.root / n)}
        self._remove_partials()
        self._write_manifest(complete=False)

    def path(self, name: str) -> Path:
        """Record ``name`` (relative, may contain ``/``) in the manifest and return its final path.

        Write the file through :func:`atomic_path`; parent folders are created.

        Raises:
            OutputError: ``name`` leaves the folder (``..``, absolute) or one of its
                components is a symbolic link or not a folder (one line naming it).
        """
        target = inside(self.root, name)
        self.begin()
        if name not in self.files:
            self.files.append(name)
            self._write_manifest(complete=False)
        if target.parent != self.root:
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise oserror(target.parent, exc) from None
            inside(self.root, name)  # a link planted while the folders were made
        return target

    def save_npy(self, name: str, array: NDArray) -> Path:
        """Write ``array`` as ``name`` atomically, its sha256 recorded; returns its path."""
        def write(tmp: Path) -> None:
            with open(tmp, "wb") as handle:
                np.save(handle, array, allow_pickle=False)

        return self.write_with(name, write)

    def write_text(self, name: str, text: str) -> Path:
        """Write ``text`` (UTF-8) as ``name`` atomically, its sha256 recorded; returns its path."""
        return self.write_with(name, lambda tmp: tmp.write_text(text, encoding="utf-8"))

    def write_with(self, name: str, writer: Callable[[Path], Any]) -> Path:
        """Call ``writer(tmp_path)`` and rename the result to ``name`` (e.g. a PNG or a plot).

        The file's sha256 goes into the manifest before the file appears under ``name``.
        """
        path = self.path(name)
        with atomic_path(path, before_rename=lambda tmp: self._record_hash(name, tmp)) as tmp:
            writer(tmp)
        return path

    def _record_hash(self, name: str, path: Path) -> None:
        self.hashes[name] = sha256_file(path)
        self._write_manifest(complete=False)

    def _hash_unrecorded(self) -> None:
        """Record the sha256 of listed files written without :meth:`write_with` (observers, checkpoints)."""
        for name in self.files:
            if name not in self.hashes and name.split("/")[0] not in self._existing:
                target = regular_file_inside(self.root, name)
                if target is not None:
                    with contextlib.suppress(OSError):
                        self.hashes[name] = sha256_file(target)

    def adopt_new_files(self) -> None:
        """Add files that appeared since the run began (written by observer plugins) to the manifest."""
        new = self._new_files()
        if new:
            self.files.extend(new)
            self._hash_unrecorded()
            self._write_manifest(complete=False)

    def _new_files(self) -> list[str]:
        """Regular files below the folder, reached without links, that no one has listed yet."""
        known = set(self.files) | self._existing | {MANIFEST, LOCK}
        names = [n for n in walk_files(self.root) if n not in known and n.split("/")[0] not in self._existing]
        return [n for n in names if not Path(n).name.startswith(PARTIAL)]

    # -- checkpoints -----------------------------------------------------------------
    def save_checkpoint(self, checkpoint: Checkpoint) -> None:
        """Write ``checkpoints/level_<k>.npz`` (and drop the older ones)."""
        name = f"{CHECKPOINTS}/level_{checkpoint.level}.npz"
        path = self.path(name)
        checkpoint.save(path)
        self._record_hash(name, path)
        for older in range(1, checkpoint.level):
            target = regular_file_inside(self.root, f"{CHECKPOINTS}/level_{older}.npz")
            if target is not None:
                with contextlib.suppress(OSError):
                    target.unlink()

    def last_checkpoint(self) -> Checkpoint | None:
        """Return the latest complete checkpoint in the folder (never one reached through a link), or None."""
        found = sorted(((int(p.stem.split("_")[1]), p) for p in (self.root / CHECKPOINTS).glob("level_*.npz")
                        if p.stem.split("_")[1].isdigit()
                        and regular_file_inside(self.root, f"{CHECKPOINTS}/{p.name}") is not None), reverse=True)
        return Checkpoint.load(found[0][1]) if found else None

    # -- finishing -------------------------------------------------------------------
    def commit(self, summary_text: str) -> None:
        """Record every output, write ``summary_text`` as the final file (``run.json``) last, drop the checkpoints."""
        self.adopt_new_files()
        self._hash_unrecorded()
        if self.final not in self.files:
            self.files.append(self.final)
        target = inside(self.root, self.final)
        self.hashes[self.final] = hashlib.sha256(summary_text.encode("utf-8")).hexdigest()
        self._write_manifest(complete=True)
        write_text(target, summary_text)
        self._committed = True
        checkpoints = self.root / CHECKPOINTS
        if checkpoints.is_dir() and not checkpoints.is_symlink():
            shutil.rmtree(checkpoints, ignore_errors=True)
        self.files = [n for n in self.files if not n.startswith(f"{CHECKPOINTS}/")]
        self.hashes = {n: h for n, h in self.hashes.items() if n in self.files}
        self._write_manifest(complete=True)

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        try:
            if kind is not None and not self._committed:
                # a hang seen on a Dask worker arrives as PluginHung, not as an interrupt: kept as on Ctrl-C
                self._abandon(keep_checkpoints=issubclass(kind, (KeyboardInterrupt, PluginHung)))
        finally:
            self._unlock()

    def _abandon(self, keep_checkpoints: bool) -> None:
        """After a failure: remove this run's files (an interrupted run keeps its checkpoints)."""
        if self._begun:
            self.files.extend(self._new_files())
            self._hash_unrecorded()
        self._remove_partials()
        if keep_checkpoints and self.last_checkpoint_exists():
            keep = [n for n in self.files if n.startswith(f"{CHECKPOINTS}/") or n == "spec.yaml"]
            self._remove([n for n in self.files if n not in keep], self.hashes)
            self.files = keep
            with contextlib.suppress(OutputError):
                self._write_manifest(complete=False)
            return
        if self._begun:
            self._remove(self.files, self.hashes)
            self._remove([MANIFEST], None)
        if self._created:
            with contextlib.suppress(OSError):
                if not [p for p in self.root.iterdir() if p.name != LOCK]:
                    self._unlock()
                    self.root.rmdir()

    def last_checkpoint_exists(self) -> bool:
        """Whether the folder holds a checkpoint (a regular file, reached without a link)."""
        folder = self.root / CHECKPOINTS
        return folder.is_dir() and not folder.is_symlink() and any(
            regular_file_inside(self.root, f"{CHECKPOINTS}/{p.name}") for p in folder.glob("*.npz"))

    def _remove(self, names: Sequence[str], hashes: dict[str, str] | None) -> list[str]:
        """Delete the files ``names`` that a run wrote; return the names kept.

        A name is deleted only if it is a regular file inside the folder reached without
        a symbolic link and, with ``hashes`` (a manifest that records them), its sha256
        is the recorded one; a file this run listed but did not hash is deleted only if
        it was not in the folder before the run. Emptied sub-folders are removed.
        """
        kept: list[str] = []
        for name in names:
            target = regular_file_inside(self.root, name)
            if target is None:
                if os.path.lexists(self.root / name):
                    kept.append(name)
                continue
            if hashes is not None and not self._is_ours(name, target, hashes):
                kept.append(name)
                continue
            with contextlib.suppress(OSError):
                target.unlink()
        for folder in sorted({(self.root / n).parent for n in names}, key=lambda p: -len(p.parts)):
            with contextlib.suppress(OSError):
                while (folder != self.root and self.root in folder.parents and not folder.is_symlink()
                       and folder.is_dir() and not any(folder.iterdir())):
                    folder.rmdir()
                    folder = folder.parent
        return kept

    def _is_ours(self, name: str, target: Path, hashes: dict[str, str]) -> bool:
        expected = hashes.get(name)
        if expected is None:  # listed by this run before it was written (a failure mid-write)
            return hashes is self.hashes and name.split("/")[0] not in self._existing
        try:
            return sha256_file(target) == expected
        except OSError:
            return False

    def _remove_partials(self) -> None:
        for name in walk_files(self.root, links=True):
            if Path(name).name.startswith(PARTIAL):
                with contextlib.suppress(OSError):
                    (self.root / name).unlink()  # a link is removed, never followed

    def _write_manifest(self, complete: bool) -> None:
        hashes = {n: self.hashes[n] for n in self.files if n in self.hashes}
        write_text(self.root / MANIFEST, json.dumps({"files": self.files, "sha256": hashes, "complete": complete},
                                                    indent=1))
