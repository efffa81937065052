"""Observer: write each level's merged frames when the spec asks for them.

With ``outputs: {merged_frames: true}`` every level gets a folder ``level_<k>/`` with
``merged.npy`` ((G, H, W) float32 flux in photons/s, NaN where unobserved),
``references.npy`` ((G,) int64 reference frames) and one tone-mapped PNG per group.

These are the merged frames the level registered (with the homographies it started
from), whatever its scheme: the schemes keep them only when the dump is asked for.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from photonpano import hookimpl


@hookimpl
def photonpano_level_finished(level: Any, spec: Any, source: Any, out_dir: Path | None) -> None:
    """Dump the level's merged frames into ``out_dir/level_<k>/`` if the spec enables it (runs with a folder)."""
    merged = level.merged  # kept by every scheme when outputs.merged_frames is set
    if out_dir is None or merged is None:
        return
    import cv2
    from photonpano.outputs import atomic_path, save_npy

    folder = out_dir / f"level_{level.level}"
    folder.mkdir(exist_ok=True)
    save_npy(folder / "merged.npy", merged.flux)
    save_npy(folder / "references.npy", level.groups.reference)
    for i, image in enumerate(merged.images):
        with atomic_path(folder / f"merged_{i:04d}_frame{int(level.groups.reference[i])}.png") as tmp:
            cv2.imwrite(str(tmp), image)
