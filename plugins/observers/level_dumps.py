"""Observer: write each level's merged frames when the spec asks for them.

With ``outputs: {merged_frames: true}`` every level gets a folder ``level_<k>/`` with
``merged.npy`` ((G, H, W) float32 flux in photons/s, NaN where unobserved),
``references.npy`` ((G,) int64 reference frames) and one tone-mapped PNG per group.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from photonpano import hookimpl


@hookimpl
def photonpano_level_finished(level: Any, spec: Any, out_dir: Path | None) -> None:
    """Dump ``level.merged`` into ``out_dir/level_<k>/`` if the spec enables it (not for in-memory runs)."""
    if out_dir is None or not spec.outputs.merged_frames or level.merged is None:
        return
    import cv2

    from photonpano.outputs import atomic_path, save_npy

    folder = out_dir / f"level_{level.level}"
    folder.mkdir(exist_ok=True)
    save_npy(folder / "merged.npy", level.merged.flux)
    save_npy(folder / "references.npy", level.groups.reference)
    for i, image in enumerate(level.merged.images):
        with atomic_path(folder / f"merged_{i:04d}_frame{int(level.groups.reference[i])}.png") as tmp:
            cv2.imwrite(str(tmp), image)
