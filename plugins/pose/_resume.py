"""Per-level checkpoints of ``pycolmap-sfm`` (``photonpano pose --resume``).

After each finished level :func:`save_level` hands the run's
:class:`~photonpano.pose_checkpoints.PoseCheckpoints` what the next level starts from:
the per-level rows and exposure poses, the homographies of the next merge, the
landmarks, the intrinsics in use, the COLMAP models (the one whose points are written,
and the one whose camera the next level uses, when another) and, once, the level-1
database. :func:`restore` reads the latest back (models through ``pycolmap``'s own
reader, so every double is the one written).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._colmap import Landmarks

__all__ = ["LevelState", "save_level", "restore"]


@dataclass
class LevelState:
    """What ``pycolmap-sfm``'s level loop carries from one level to the next.

    Attributes:
        level: the last finished level.
        levels: its ``run.json`` rows, levels 1..level.
        exposures: per level, (G,) int64 reference frames and (G, 4, 4) float64 poses.
        homographies: (T, 3, 3) float64 per-frame homographies of the next level's merge.
        landmarks: the 2D-3D observations the next level registers against.
        used: the :class:`~photonpano.pose.Intrinsics` in use.
        current: the ``pycolmap.Reconstruction`` whose camera the next level uses.
        final: the ``pycolmap.Reconstruction`` whose points are written.
        database: the level-1 COLMAP database (a path in the work folder).
    """

    level: int
    levels: list[dict[str, Any]]
    exposures: list[tuple[NDArray[np.int64], NDArray[np.float64]]]
    homographies: NDArray[np.float64]
    landmarks: Landmarks
    used: Any
    current: Any
    final: Any
    database: Path


def save_level(store: Any, state: LevelState, work_dir: Path) -> None:
    """Save ``state`` as the checkpoint of ``state.level`` (nothing without a store).

    Args:
        store: a :class:`~photonpano.pose_checkpoints.PoseCheckpoints`, or None.
        state: the state after the level.
        work_dir: the estimator's work folder (the models are written there first).
    """
    if store is None:
        return
    arrays: dict[str, NDArray[Any]] = {"homographies": state.homographies, "landmark_frames": state.landmarks.frames,
                                       "landmark_descriptors": state.landmarks.descriptors,
                                       "landmark_xyz": state.landmarks.xyz}
    for i, (frames, poses) in enumerate(state.exposures):
        arrays[f"frames_{i}"], arrays[f"poses_{i}"] = frames, poses
    files: dict[str, Path] = {}
    models = {"final": state.final} if state.current is state.final else {"final": state.final,
                                                                          "current": state.current}
    for role, model in models.items():
        folder = work_dir / "checkpoint" / f"level_{state.level}" / role
        if folder.exists():  # a killed run's
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        model.write(str(folder))
        files.update({f"{role}/{p.name}": p for p in sorted(folder.iterdir()) if p.is_file()})
    shared = None
    if state.level == 1:
        files["database.db"] = state.database
    else:
        shared = {"database.db": (1, "database.db")}
    record = {"levels": state.levels, "used": state.used.as_dict(), "exposures": len(state.exposures)}
    store.save(state.level, arrays, record, files, shared)


def restore(store: Any, work_dir: Path) -> LevelState | None:
    """The state of the latest checkpoint in ``store`` (None: none, or no store).

    The models and the database are copied into ``work_dir/resumed/`` first (COLMAP may
    write to a database it opens; the checkpoint's files stay as they were written).
    """
    found = store.latest() if store is not None else None
    if found is None:
        return None
    import pycolmap
    from photonpano.pose import Intrinsics

    folder = work_dir / "resumed"
    if folder.exists():
        shutil.rmtree(folder)
    for name, path in found.files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, folder / name)
    final = pycolmap.Reconstruction(str(folder / "final"))
    current = pycolmap.Reconstruction(str(folder / "current")) if (folder / "current").is_dir() else final
    arrays, record = found.arrays, found.record
    exposures = [(arrays[f"frames_{i}"], arrays[f"poses_{i}"]) for i in range(record["exposures"])]
    landmarks = Landmarks(arrays["landmark_frames"], arrays["landmark_descriptors"], arrays["landmark_xyz"])
    return LevelState(found.level, record["levels"], exposures, arrays["homographies"], landmarks,
                      Intrinsics(**record["used"]), current, final, folder / "database.db")
