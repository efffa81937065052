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
        template: ``(flux, frames, homographies)`` of the panorama the next level
            registers against ((Hc, Wc) float32, (Hc, Wc) float32, (T, 3, 3) float64), or
            None where the next level does not need one.
    """

    level: int
    homographies: NDArray[np.float64]
    statistics: list[dict[str, Any]]
    template: tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]] | None = None

    def save(self, path: Path) -> None:
        """Write the checkpoint atomically as an uncompressed ``.npz``."""
        arrays = {"level": np.int64(self.level), "homographies": self.homographies,
                  "statistics": np.frombuffer(json.dumps(self.statistics, default=json_default).encode(),
                                              dtype=np.uint8)}
        if self.template is not None:
            arrays.update(template_flux=self.template[0], template_frames=self.template[1],
                          template_homographies=self.template[2])
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
                template = None
                if "template_flux" in data:
                    template = (data["template_flux"], data["template_frames"], data["template_homographies"])
                return cls(int(data["level"]), data["homographies"],
                           json.loads(data["statistics"].tobytes().decode()), template)
        except (OSError, ValueError, KeyError, EOFError) as exc:
            raise OutputError(f"checkpoint {path} is not readable ({type(exc).__name__}); "
                              "rerun with --force") from None
