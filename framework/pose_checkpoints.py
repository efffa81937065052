"""Per-level checkpoints of a pose estimator, for ``photonpano pose --resume``.

A pose run (:func:`photonpano.pose_run.run_pose`) hands its estimator a
:class:`PoseCheckpoints` store. After each finished level the estimator saves what the
next level starts from: arrays (poses, homographies, landmarks), a JSON-able record
(per-level statistics, intrinsics) and files (COLMAP models, its database), under
``checkpoints/pose_<k>/`` of the run folder, each written atomically and recorded in
the manifest; ``checkpoints/pose_<k>.npz`` comes last and marks level ``k`` complete.
A resumed run reads the latest complete checkpoint back and continues after it, so
everything checkpointed is reused bit for bit, and (``pycolmap-sfm`` running COLMAP
single-threaded and reseeding each level) the levels after it come out as in an
uninterrupted run. The checkpoints go with the run's other checkpoints when the run
completes.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .outputs.checkpoint import CHECKPOINTS
from .outputs.files import json_default, regular_file_inside

__all__ = ["PoseCheckpoint", "PoseCheckpoints"]


@dataclass(frozen=True)
class PoseCheckpoint:
    """The state a pose estimator saved after a finished level.

    Attributes:
        level: the last finished level (1-based).
        arrays: the arrays saved, by name (as saved: dtype and shape kept).
        record: the JSON-able record saved (e.g. per-level statistics).
        files: the files saved, by name: paths inside the run folder's checkpoints
            (read them or copy them; do not change them).
    """

    level: int
    arrays: dict[str, NDArray[Any]]
    record: dict[str, Any]
    files: dict[str, Path]


class PoseCheckpoints:
    """The checkpoints of one pose run in its run folder (see the module).

    Args:
        folder: the :class:`~photonpano.outputs.RunFolder` of the run (begun).
    """

    def __init__(self, folder: Any) -> None:
        """Keep the checkpoints of ``folder``."""
        self.folder = folder

    def save(self, level: int, arrays: dict[str, NDArray[Any]], record: dict[str, Any],
             files: dict[str, Path] | None = None, shared: dict[str, tuple[int, str]] | None = None) -> None:
        """Save the state after ``level``: ``files`` first (copied), the arrays and record last.

        Args:
            level: the finished level (1-based).
            arrays: numeric arrays by name (no object arrays).
            record: JSON-able values (numpy scalars allowed).
            files: files to copy into ``checkpoints/pose_<level>/`` by name (a name may
                contain ``/``).
            shared: files saved by an earlier level's checkpoint and still valid, by name:
                ``(level, name there)`` (not copied again, e.g. a database written once).

        Raises:
            OutputError: a file cannot be written (one line naming it).
        """
        names = {}
        for name, source in (files or {}).items():
            target = f"{CHECKPOINTS}/pose_{level}/{name}"
            self.folder.write_with(target, lambda tmp, source=source: shutil.copyfile(source, tmp))
            names[name] = target
        for name, (earlier, there) in (shared or {}).items():
            names[name] = f"{CHECKPOINTS}/pose_{earlier}/{there}"
        meta = json.dumps({"level": level, "record": record, "files": names}, default=json_default)

        def write(tmp: Path) -> None:
            payload: dict[str, Any] = {f"array_{k}": np.asarray(v) for k, v in arrays.items()}
            with open(tmp, "wb") as handle:
                np.savez(handle, meta=np.frombuffer(meta.encode(), np.uint8), **payload)

        self.folder.write_with(f"{CHECKPOINTS}/pose_{level}.npz", write)

    def latest(self) -> PoseCheckpoint | None:
        """The latest complete checkpoint (every file it names present), or None.

        A damaged or incomplete checkpoint (a run killed while writing it) is passed
        over for the one before it. Files reached through a symbolic link do not count.
        """
        root = self.folder.root
        found = []
        for path in (root / CHECKPOINTS).glob("pose_*.npz"):
            stem = path.stem.split("_", 1)[1]
            if stem.isdigit() and regular_file_inside(root, f"{CHECKPOINTS}/{path.name}") is not None:
                found.append((int(stem), path))
        for level, path in sorted(found, reverse=True):
            try:
                with np.load(path, allow_pickle=False) as data:
                    meta = json.loads(data["meta"].tobytes().decode())
                    arrays = {k[len("array_"):]: data[k] for k in data.files if k.startswith("array_")}
            except (OSError, ValueError, KeyError, EOFError):
                continue
            files = {name: regular_file_inside(root, target) for name, target in meta["files"].items()}
            if meta.get("level") == level and all(p is not None for p in files.values()):
                return PoseCheckpoint(level, arrays, meta["record"], files)  # type: ignore[arg-type]
        return None
