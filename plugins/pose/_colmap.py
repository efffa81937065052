"""COLMAP helpers of ``pycolmap-sfm``: databases of virtual exposures, model poses, 2D-3D landmarks."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

THREADS = 1
"""Threads COLMAP's extraction, matching, mapping and triangulation may use. One: with more, the
order in which threads finish changes the matches and the mapper's choices, and two runs of the
same spec differed (level 2 of a 3000-frame simulate3d run registered 0 and 10 of 13 exposures);
with one, a run is reproducible, which ``pose --resume`` needs to equal an uninterrupted run."""


class Landmarks(NamedTuple):
    """Level-1 model observations: (K,) int64 frames, (K, 128) float32 unit descriptors, (K, 3) points."""

    frames: NDArray[np.int64]
    descriptors: NDArray[np.float32]
    xyz: NDArray[np.float64]


def camera_intrinsics(rec: Any) -> Any:
    """The :class:`photonpano.pose.Intrinsics` of ``rec``'s first camera (OpenCV pixel centres).

    Works for COLMAP's ``PINHOLE`` (fx, fy, cx, cy) and ``SIMPLE_*`` / ``RADIAL`` models
    (f, cx, cy, ...); distortion parameters are left out.
    """
    from photonpano.pose import Intrinsics

    camera = next(iter(rec.cameras.values()))
    params = [float(v) for v in camera.params]
    fx, fy, cx, cy = params[:4] if camera.model.name in ("PINHOLE", "OPENCV") else (params[0], *params[:3])
    return Intrinsics(fx, fy, cx - 0.5, cy - 0.5)


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
    desc = np.asarray(descriptors, np.float32).reshape(-1, 128)
    desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return Landmarks(np.asarray(frames, np.int64), desc, np.asarray(xyz, np.float64).reshape(-1, 3))


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
    pycolmap.set_random_seed(seed)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_params is not None:
        reader.camera_params = ",".join(f"{v:.12g}" for v in camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = cfg.max_features
    extraction.num_threads = THREADS
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = THREADS
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
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pycolmap.match_sequential(
            database,
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    advance(1)
    return database, image_dir


def refine_tracks(
    rec: Any, images: dict[int, NDArray[np.uint8]], window: int, max_shift_px: float
) -> dict[str, float]:
    """Re-locate every track's observations by Lucas-Kanade alignment to one reference observation.

    SIFT keypoints of the same scene point move by about a pixel from one virtual exposure
    to the next (detector noise on photon-noisy images), and a 1 mm sideways error of the
    camera shows as only ~0.03 px of parallax in the simulated room, so their noise sets the
    poses' noise.
    Aligning the patch around each observation to the patch around the track's
    observation in the exposure nearest the middle of the track in time (pyramidal
    Lucas-Kanade, translation only; Bouguet, "Pyramidal implementation of the Lucas
    Kanade feature tracker", OpenCV 2000) makes the observations of a track consistent
    with each other; the reference keypoint's own error is common to the whole track
    and moves the 3D point, not the poses. Observations that do not converge or move
    more than ``max_shift_px`` are deleted from the track (bundle-adjust afterwards).

    Args:
        rec: ``pycolmap.Reconstruction``, modified in place (keypoints ``xy`` in COLMAP
            pixels: centres at +0.5).
        images: image id -> (H, W) uint8 virtual exposure of that image.
        window: side of the aligned square patch in pixels (>= 5).
        max_shift_px: largest accepted move of a keypoint in pixels.

    Returns:
        ``{"moved_px": median move of the kept observations, "deleted": count}``.
    """
    import cv2

    frame = {image_id: int(Path(image.name).stem) for image_id, image in rec.images.items()}
    jobs: dict[tuple[int, int], list[tuple[NDArray[np.float64], int]]] = {}
    for point in rec.points3D.values():
        elements = [(e.image_id, e.point2D_idx) for e in point.track.elements]
        order = np.argsort([frame[image_id] for image_id, _ in elements], kind="stable")
        ref_image, ref_index = elements[order[len(order) // 2]]
        ref_xy = rec.images[ref_image].points2D[ref_index].xy
        for image_id, index in elements:
            if image_id != ref_image:
                jobs.setdefault((ref_image, image_id), []).append((ref_xy, index))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-3)
    moved, delete = [], []
    for (ref_image, image_id), items in jobs.items():
        keypoints = rec.images[image_id].points2D
        # OpenCV puts pixel centres at integers, COLMAP at +0.5
        start = np.array([xy for xy, _ in items], np.float32).reshape(-1, 1, 2) - 0.5
        guess = np.array([keypoints[i].xy for _, i in items], np.float32).reshape(-1, 1, 2) - 0.5
        found, status, _ = cv2.calcOpticalFlowPyrLK(
            images[ref_image],
            images[image_id],
            start,
            guess.copy(),
            winSize=(window, window),
            maxLevel=1,
            criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        shift = np.linalg.norm(found - guess, axis=2).ravel()
        keep = (status.ravel() == 1) & (shift < max_shift_px)
        for (_, index), xy, ok, step in zip(items, found.reshape(-1, 2) + 0.5, keep, shift):
            if ok:
                keypoints[index].xy = xy.astype(np.float64)
                moved.append(step)
            else:
                delete.append((image_id, index))
    for image_id, index in delete:
        if rec.images[image_id].points2D[index].has_point3D():
            rec.delete_observation(image_id, index)
    return {"moved_px": float(np.median(moved)) if moved else 0.0, "deleted": len(delete)}


def prune_observations(rec: Any, factor: float) -> dict[str, float]:
    """Delete observations whose reprojection error exceeds ``factor`` times the median one.

    After :func:`refine_tracks` most observations reproject within a fraction of a pixel
    and the rest (wrong matches, occlusion edges, patches that drifted) would pull the
    poses; bundle-adjust afterwards.

    Args:
        rec: ``pycolmap.Reconstruction`` with poses and points, modified in place.
        factor: threshold as a multiple of the median reprojection error (> 0).

    Returns:
        ``{"threshold_px": the threshold in pixels, "pruned": observations deleted}``.
    """
    observations, errors = [], []
    for point in rec.points3D.values():
        for element in point.track.elements:
            image = rec.images[element.image_id]
            projected = image.project_point(point.xyz)
            xy = image.points2D[element.point2D_idx].xy
            observations.append((element.image_id, element.point2D_idx))
            errors.append(np.inf if projected is None else float(np.linalg.norm(np.asarray(projected) - xy)))
    if not errors:
        return {"threshold_px": 0.0, "pruned": 0}
    threshold = factor * float(np.median(errors))
    pruned = 0
    for (image_id, index), error in zip(observations, errors):
        if error > threshold and rec.images[image_id].points2D[index].has_point3D():
            rec.delete_observation(image_id, index)
            pruned += 1
    return {"threshold_px": threshold, "pruned": pruned}


def map_exposures(config: Any, images: NDArray[np.uint8], references: NDArray[np.int64], folder: Path,
                  intrinsics: Any, progress: Any) -> tuple[Any, Any, Path | None]:
    """Run COLMAP on the level-1 exposures.

    Returns:
        ``(reconstruction, intrinsics, database)``: the largest ``pycolmap.Reconstruction``
        or None, the intrinsics (given, or COLMAP's), and the database it came from (None
        without a reconstruction).

    Up to ``attempts`` seeds; self-calibrated, when an exposure is left out, also with
    the focal length held at 1.0, 0.8 and 0.6 x the larger image side.
    """
    import shutil

    import pycolmap

    cfg = config
    model, params = (
        ("PINHOLE", intrinsics.colmap_params()) if intrinsics is not None else ("SIMPLE_RADIAL", None)
    )
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = THREADS
    # a sideways path of a few decimetres at metres' depth: small triangulation angles
    options.mapper.init_min_tri_angle = cfg.min_angle_deg
    if intrinsics is not None:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
    rec, kept = None, None
    for attempt in range(cfg.attempts):
        # COLMAP's verification and mapper can settle on a poor initial pair: other seeds
        database, image_dir = write_and_match(
            config, images, references, folder, model, params, progress, 1, seed=cfg.seed + attempt
        )
        if attempt == 0:
            first = database
        options.random_seed = cfg.seed + attempt
        models = pycolmap.incremental_mapping(database, image_dir, folder / f"sparse_{attempt}", options)
        best = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
        if best is not None and (rec is None or best.num_reg_images() > rec.num_reg_images()):
            rec, kept = best, database
        if rec is not None and rec.num_reg_images() >= cfg.min_registered * len(images):
            break
    if intrinsics is None and (rec is None or rec.num_reg_images() < len(images)):
        # self-calibration can run away with the focal length on a short path (seen: 1454 px
        # for 420, half the exposures registered): map again with the focal length held at
        # a few values; levels >= 2 refine it (refine_intrinsics)
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
        options.random_seed = cfg.seed
        side = float(max(images.shape[1:3]))
        for scale in (1.0, 0.8, 0.6):
            database = folder / f"database_focal_{scale}.db"
            shutil.copyfile(first, database)
            db = pycolmap.Database.open(str(database))
            try:
                camera = db.read_all_cameras()[0]
                camera.params = [scale * side, camera.params[1], camera.params[2], 0.0]
                camera.has_prior_focal_length = True
                db.update_camera(camera)
            finally:
                db.close()
            models = pycolmap.incremental_mapping(database, image_dir, folder / f"sparse_focal_{scale}", options)
            best = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
            if best is not None and (rec is None or best.num_reg_images() > rec.num_reg_images()):
                rec, kept = best, database
            if rec is not None and rec.num_reg_images() == len(images):
                break
    if rec is None:
        return None, intrinsics, None
    return rec, intrinsics if intrinsics is not None else camera_intrinsics(rec), kept


def localise(config: Any, images: NDArray[np.uint8], references: NDArray[np.int64], rec: Any, landmarks: Landmarks,
             progress: Any, level: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Register each exposure against the level-1 model (SIFT, ratio test, LO-RANSAC P3P + refinement).

    Args:
        config: the ``pycolmap-sfm`` config (``max_features``, ``max_error_px``,
            ``localise_neighbours``, ``min_inliers``).
        images: (G, H, W) uint8 exposures.
        references: (G,) int64 reference frame of each exposure.
        rec: the level-1 ``pycolmap.Reconstruction`` (its camera is used).
        landmarks: the level-1 model's observations (:func:`model_landmarks`).
        progress: ``progress(task, total)`` returning ``advance(n)``, or None.
        level: the level number (for the progress label, and the random seed ``seed + level``
            COLMAP starts it from, so that a level's result does not depend on whether the
            levels before it ran in this process or were restored by ``--resume``).

    Returns:
        ``(poses, inliers)``: (G, 4, 4) camera-to-world poses (NaN where it failed) and
        (G,) float inlier counts (NaN where it failed).
    """
    import cv2
    import pycolmap

    cfg = config
    pycolmap.set_random_seed(cfg.seed + level)
    camera = next(iter(rec.cameras.values()))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = cfg.max_features
    extraction.num_threads = THREADS
    sift = pycolmap.FeatureExtractor.create(extraction, device=pycolmap.Device.cpu)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    model_frames = np.unique(landmarks.frames)
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = cfg.max_error_px
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = False
    refinement.refine_extra_params = False
    poses = np.full((len(images), 4, 4), np.nan)
    inliers = np.full(len(images), np.nan)
    advance = progress(f"level {level}: register", len(images)) if progress else (lambda k: None)
    for g, (image, ref) in enumerate(zip(images, references)):
        features, described = sift.extract_from_uint8_array(np.ascontiguousarray(image))
        keypoints = np.asarray(pycolmap.keypoints_to_matrix(features), np.float64)
        desc = described.data.astype(np.float32)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        near = model_frames[np.argsort(np.abs(model_frames - ref))[: cfg.localise_neighbours]]
        pick = np.flatnonzero(np.isin(landmarks.frames, near))
        pairs = matcher.knnMatch(desc, landmarks.descriptors[pick], k=2)
        good = [
            (m.queryIdx, pick[m.trainIdx])
            for m, *rest in pairs
            if rest and m.distance < 0.8 * rest[0].distance
        ]
        if len(good) >= 12:
            q, t = np.array(good).T
            found = pycolmap.estimate_and_refine_absolute_pose(
                keypoints[q, :2], landmarks.xyz[t], camera, estimation, refinement
            )
            if found is not None and found["num_inliers"] >= cfg.min_inliers:
                poses[g] = np.vstack([found["cam_from_world"].inverse().matrix(), [0, 0, 0, 1]])
                inliers[g] = found["num_inliers"]
        advance(1)
    return poses, inliers
