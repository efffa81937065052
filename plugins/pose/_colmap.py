"""COLMAP helpers of ``pycolmap-sfm``: databases of virtual exposures, model poses, 2D-3D landmarks."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray


class Landmarks(NamedTuple):
    """Level-1 model observations: (K,) int64 frames, (K, 128) float32 unit descriptors, (K, 3) points."""

    frames: NDArray[np.int64]
    descriptors: NDArray[np.float32]
    xyz: NDArray[np.float64]


def model_poses(rec: Any, references: NDArray[np.int64]) -> NDArray[np.float64]:
    """(G, 4, 4) camera-to-world poses of ``rec``'s images, named by reference frame (NaN if absent)."""
    poses = np.full((len(references), 4, 4), np.nan)
    for image in rec.images.values() if rec is not None else ():
        if image.has_pose:
            index = np.searchsorted(references, int(Path(image.name).stem))
            poses[index] = np.vstack([image.cam_from_world().inverse().matrix(), [0, 0, 0, 1]])
    return poses


def model_landmarks(rec: Any, database: Path) -> Landmarks:
    """The level-1 model's 2D-3D observations: per registered image, descriptors and 3D points."""
    import pycolmap

    frames, descriptors, xyz = [], [], []
    db = pycolmap.Database.open(str(database))
    try:
        for image_id, image in rec.images.items():
            if not image.has_pose:
                continue
            data = db.read_descriptors(image_id).data
            for idx, point in enumerate(image.points2D):
                if point.has_point3D():
                    frames.append(int(Path(image.name).stem))
                    descriptors.append(data[idx])
                    xyz.append(rec.points3D[point.point3D_id].xyz)
    finally:
        db.close()
    desc = np.asarray(descriptors, np.float32)
    desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return Landmarks(np.asarray(frames, np.int64), desc, np.asarray(xyz, np.float64))


def write_and_match(
    config: Any,
    images: NDArray[np.uint8],
    references: NDArray[np.int64],
    folder: Path,
    camera_model: str,
    camera_params: list[float] | None,
    progress: Any,
    level: int,
    seed: int = 0,
) -> tuple[Path, Path]:
    """Write the exposures as PNGs named by reference frame, extract SIFT and match (COLMAP database)."""
    import cv2
    import pycolmap

    cfg = config
    image_dir = folder / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for image, ref in zip(images, references):
        names.append(f"{int(ref):08d}.png")
        cv2.imwrite(str(image_dir / names[-1]), image)
    database = folder / f"database_{seed}.db"
    database.unlink(missing_ok=True)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    pycolmap.logging.minloglevel = 2
    pycolmap.set_random_seed(seed)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_params is not None:
        reader.camera_params = ",".join(f"{v:.12g}" for v in camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = cfg.max_features
    advance = progress(f"level {level}: features and matches", 2) if progress else (lambda k: None)
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    advance(1)
    if cfg.matching == "exhaustive" or (cfg.matching == "auto" and len(names) <= cfg.exhaustive_max):
        pycolmap.match_exhaustive(database, verification_options=verification, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pycolmap.match_sequential(
            database,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    advance(1)
    return database, image_dir
