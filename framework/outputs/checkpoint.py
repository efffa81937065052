"""Per-level checkpoints: what the next level needs, for ``--resume``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import OutputError
from .files import atomic_path, json_default

__all__ = ["CHECKPOINTS", "Checkpoint"]

CHECKPOINTS = "checkpoints"
"""Sub-folder of the per-level checkpoints ``level_<k>.npz``."""


@dataclass
class Checkpoint:
    """The state after a finished level, from which the next level starts.

    Attributes:
        level: the last finished level (1-based).
        homographies: (T, 3, 3) float64 per-frame homographies after that level, in the
            level loop's working coordinates (before the final middle-frame gauge).
        statistics: the ``run.json`` statistics rows of levels 1..level.
    """

    level: int
    homographies: NDArray[np.float64]
    statistics: list[dict[str, Any]]

    def save(self, path: Path) -> None:
        """Write the checkpoint atomically as an uncompressed ``.npz``."""
        arrays = {"level": np.int64(self.level), "homographies": self.homographies,
                  "statistics": np.frombuffer(json.dumps(self.statistics, default=json_default).encode(),
                                              dtype=np.uint8)}
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.savez(handle, **arrays)

    @classmethod
    def load(cls, path: Path) -> Checkpoint:
        """Read a checkpoint written by :meth:`save`.

        Raises:
            OutputError: an unreadable or incomplete checkpoint, naming ``path``.
        """
        try:
            with np.load(path, allow_pickle=False) as data:
                return cls(int(data["level"]), data["homographies"],
                           json.loads(data["statistics"].tobytes().decode()))
        except (OSError, ValueError, KeyError, EOFError) as exc:
            raise OutputError(f"checkpoint {path} is not readable ({type(exc).__name__}); "
                              "rerun with --force") from None
