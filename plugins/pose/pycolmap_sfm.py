"""Pose estimator ``pycolmap-sfm`` (experimental): stratified structure from motion on virtual exposures.

Level 1 is the plain baseline: the capture is cut into groups of m binary frames, each
merged without motion compensation into a flux image (``flux-mle``), tone-mapped to
8 bits and given to COLMAP (SIFT, sequential or exhaustive matching, incremental
mapping with the known intrinsics, or self-calibration without them). Each later level
re-samples with ``midpoint`` (groups between the previous ones, so twice as many
exposures) and re-merges every group with the plane-induced homographies of the
current pose estimate (a fronto-parallel plane at the median depth of the sparse
points), so the new virtual exposures are sharp at their centre frame; they are
registered against the model, triangulated and bundle-adjusted, every track's keypoints
are re-located by patch alignment to one reference observation (SIFT's keypoint noise
would otherwise set the poses' noise), outlying observations are dropped and the model
adjusted again. The poses are interpolated to every binary frame (SE(3): slerp + cubic).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import StageError
from photonpano.stages import PhotonSource, PoseEstimator, PoseEstimatorConfig
from pydantic import Field, field_validator

from ._colmap import (
    THREADS,
    Landmarks,
    camera_intrinsics,
    localise,
    map_exposures,
    model_landmarks,
    model_poses,
    prune_observations,
    refine_tracks,
    write_and_match,
)
from ._colmap_log import colmap_log
from ._resume import LevelState, restore, save_level


class PycolmapSfMConfig(PoseEstimatorConfig):
    """Camera poses by COLMAP structure from motion on stratified, motion-compensated virtual exposures."""

    plugin: Literal["pycolmap-sfm"] = "pycolmap-sfm"
    requires = ("pycolmap",)
    install_hint = "pip install 'photonpano[colmap]'"
    group_size: Annotated[int, Field(ge=2)] = 1000
    """Binary frames per virtual exposure m."""
    levels: Annotated[int, Field(ge=1, le=6)] = 3
    """Number of levels; level 1 is naive averaging, each later level doubles the exposures
    and merges them with the previous level's poses."""
    growth: Annotated[float, Field(ge=0.25, le=1)] = 0.5
    """Group length at level k is m * growth**(k-1) frames: motion compensation is exact
    only on the dominant plane, so shorter groups smear nearer and farther surfaces less."""
    matching: Literal["auto", "sequential", "exhaustive"] = "auto"
    """COLMAP matching: each exposure with its ``overlap`` neighbours in time (and 2^k
    further ones), every pair, or ``auto``: every pair up to ``exhaustive_max`` exposures."""
    exhaustive_max: Annotated[int, Field(ge=2)] = 100
    """auto matching: the most exposures matched exhaustively."""
    overlap: Annotated[int, Field(ge=1)] = 12
    """sequential matching: neighbours matched on each side (and 2^k further ones)."""
    max_features: Annotated[int, Field(ge=100)] = 4096
    """SIFT features per exposure."""
    min_photons: Annotated[float, Field(gt=0)] = 2.0
    """Refuse captures whose level-1 exposures collect fewer photons per pixel on average
    (too dark to register)."""
    min_registered: Annotated[float, Field(gt=0, le=1)] = 0.5
    """Fail when less than this fraction of the level-1 exposures registers."""
    max_error_px: Annotated[float, Field(gt=0)] = 2.0
    """Levels >= 2: RANSAC threshold of the absolute pose (reprojection error, pixels)."""
    localise_neighbours: Annotated[int, Field(ge=1)] = 3
    """Levels >= 2: an exposure is matched against the model images of this many level-1
    exposures nearest in time."""
    min_inliers: Annotated[int, Field(ge=6)] = 30
    """Levels >= 2: fewest 2D-3D inliers that register an exposure."""
    min_angle_deg: Annotated[float, Field(gt=0)] = 2.0
    """Smallest triangulation angle of COLMAP's initial image pair in degrees (COLMAP's
    default 16 suits orbits, not a camera travelling a fraction of the scene depth)."""
    attempts: Annotated[int, Field(ge=1)] = 3
    """Level 1: mapping attempts (other seeds) while fewer than ``min_registered`` exposures register."""
    relocalise: bool = True
    """Levels >= 3: register against the previous level's bundle-adjusted model (else level 1's)."""
    bundle_adjust: bool = True
    """Levels >= 2: triangulate the registered exposures' matches and bundle-adjust their poses
    and points together (else keep the poses of the single-image registration)."""
    track_window: Annotated[int, Field(ge=0)] = 21
    """Levels >= 2, after the bundle adjustment: re-locate each track's keypoints by
    Lucas-Kanade alignment of patches of this side (pixels) to the track's middle
    observation, then bundle-adjust again; 0 keeps COLMAP's SIFT keypoints."""
    track_max_shift_px: Annotated[float, Field(gt=0)] = 3.0
    """Track refinement: observations that move further than this (pixels) or do not
    converge are dropped from their tracks."""
    track_prune: Annotated[float, Field(ge=0)] = 3.0
    """Track refinement: then drop observations whose reprojection error exceeds this
    multiple of the median one and bundle-adjust again (0: keep them)."""
    refine_intrinsics: bool = True
    """Self-calibration (no intrinsics given): the bundle adjustments of levels >= 2 also
    refine the focal length and radial distortion, on the sharper exposures (the principal
    point stays at COLMAP's estimate)."""
    seed: Annotated[int, Field(ge=0)] = 0
    """Random seed of COLMAP's RANSAC and mapper."""

    @field_validator("track_window")
    @classmethod
    def _window(cls, value: int) -> int:
        if 0 < value < 5:
            raise ValueError("track_window must be 0 (off) or at least 5 pixels")
        return value

    def build(self) -> PycolmapSfM:
        """Return the estimator."""
        self.check_available()
        return PycolmapSfM(self)


class PycolmapSfM(PoseEstimator):
    """Stratified structure from motion with pycolmap (see the module doc)."""

    def __init__(self, config: PycolmapSfMConfig) -> None:
        self.config = config
        self._database: Path | None = None  # the COLMAP database of the kept level-1 model
        self._calibrate = False  # levels >= 2 refine the camera (self-calibration)

    def estimate(self, source: PhotonSource, intrinsics: Any, work_dir: Path, progress: Any = None,
                 checkpoints: Any = None) -> Any:
        """Estimate poses level by level (see :meth:`PoseEstimator.estimate`).

        COLMAP's log goes to the logger ``photonpano.colmap`` (:func:`colmap_log`), not to stderr.
        With ``checkpoints`` (a :class:`~photonpano.pose_checkpoints.PoseCheckpoints`),
        each finished level is saved there and a run starts after the latest level saved
        (:mod:`._resume`), reusing its results bit for bit.

        Raises:
            StageError: capture too short (fewer than 3 m frames) or too dark, or too few
                exposures registered at level 1.
        """
        with colmap_log():
            return self._estimate(source, intrinsics, work_dir, progress, checkpoints)

    def _estimate(self, source: PhotonSource, intrinsics: Any, work_dir: Path, progress: Any, store: Any) -> Any:
        from photonpano.executor import make_executor
        from photonpano.plugins.mergers.flux_mle import FluxMLEConfig
        from photonpano.plugins.resamplers.midpoint import MidpointConfig
        from photonpano.pose import PoseResult, dominant_plane, interpolate_poses, plane_homographies

        cfg, n = self.config, source.n_frames
        self._calibrate = intrinsics is None and cfg.refine_intrinsics
        if n < 3 * cfg.group_size:
            raise StageError(
                "pose_estimator",
                "pycolmap-sfm",
                f"the capture has {n} binary frames; at least "
                f"3 x group_size = {3 * cfg.group_size} are needed (lower group_size)",
            )
        resampler, merger = MidpointConfig(growth=cfg.growth).build(), FluxMLEConfig().build()
        executor = make_executor("threads")
        homographies = np.repeat(np.eye(3)[None], n, axis=0)
        levels: list[dict[str, Any]] = []
        exposures: list[tuple[NDArray[np.int64], NDArray[np.float64]]] = []
        rec: Any = None  # a pycolmap.Reconstruction (pycolmap is untyped)
        landmarks: Landmarks | None = None
        final = None  # the model whose points are written: level 1's or the last bundle adjustment's
        done = restore(store, work_dir)  # a resumed run: the levels finished before it was stopped
        if done is not None:
            levels, exposures, homographies, landmarks = done.levels, done.exposures, done.homographies, done.landmarks
            used, current, final, self._database = done.used, done.current, done.final, done.database
        for level in range(1 if done is None else done.level + 1, cfg.levels + 1):
            t0 = time.perf_counter()
            groups = resampler.groups(n, cfg.group_size, level)
            advance = progress(f"level {level}: merge", len(groups)) if progress else None
            merged = merger.merge(source, homographies, groups, progress=advance, executor=executor)
            if level == 1:
                self._check_light(source, merged)
            t_merge = time.perf_counter() - t0
            t0 = time.perf_counter()
            if level == 1:
                rec, used, self._database = map_exposures(
                    cfg, merged.images, groups.reference, work_dir / "level_1", intrinsics, progress
                )
                poses, inliers, final = model_poses(rec, groups.reference), None, rec
                current = rec  # the model whose camera the next level uses
            else:
                assert landmarks is not None  # set at level 1
                poses, inliers = localise(
                    cfg, merged.images, groups.reference, current, landmarks, progress, level
                )
                if cfg.bundle_adjust and np.isfinite(poses[:, 0, 0]).sum() >= 3:  # else kept below
                    poses, refined, tracks = self._refine(
                        merged.images,
                        groups.reference,
                        poses,
                        current,
                        work_dir / f"level_{level}",
                        progress,
                        level,
                    )
            registered = int(np.isfinite(poses[:, 0, 0]).sum())
            row = {
                "level": level,
                "exposures": len(groups),
                "registered": registered,
                "timings_s": {"merge": t_merge, "register": time.perf_counter() - t0},
            }
            if level == 1:
                row.update(
                    points=int(rec.num_points3D()) if rec is not None else 0,
                    reprojection_error_px=float(rec.compute_mean_reprojection_error()) if rec else None,
                )
                if registered < max(3, cfg.min_registered * len(groups)):
                    raise StageError(
                        "pose_estimator",
                        "pycolmap-sfm",
                        f"only {registered} of {len(groups)} "
                        "level-1 virtual exposures registered (too dark, too little texture or "
                        "motion, or wrong intrinsics)",
                    )
                assert self._database is not None  # None only without a model, and one registered >= 3
                landmarks = model_landmarks(rec, self._database)
            else:
                assert inliers is not None  # localise's, at every level after the first
                found = inliers[np.isfinite(inliers)]
                row.update(median_inliers=float(np.median(found)) if len(found) else 0.0)
                if registered < 3:  # keep the previous level's poses
                    row["note"] = "too few exposures registered; the previous level's poses are kept"
                    levels.append(row)
                    break
                if cfg.bundle_adjust and refined.num_points3D() < cfg.min_inliers:
                    row["note"] = (
                        f"the bundle adjustment kept {refined.num_points3D()} points; "
                        "the previous level's poses are kept"
                    )
                    levels.append(row)
                    break
                if cfg.bundle_adjust:
                    final = refined
                    if cfg.relocalise:  # the next level registers against this sharper model
                        assert self._database is not None  # kept with the level-1 model
                        landmarks = model_landmarks(refined, self._database)
                    if self._calibrate:  # its bundle adjustment refined the camera
                        current, used = refined, camera_intrinsics(refined)
                    row.update(
                        points=int(refined.num_points3D()),
                        reprojection_error_px=float(refined.compute_mean_reprojection_error()),
                    )
                    if tracks:
                        row["track_refinement"] = tracks
            levels.append(row)
            exposures.append((groups.reference.copy(), poses))
            every = interpolate_poses(groups.reference, poses, n)
            reference = poses[np.flatnonzero(np.isfinite(poses[:, 0, 0]))[registered // 2]]
            assert landmarks is not None  # set at level 1
            normal, distance = dominant_plane(landmarks.xyz, reference)
            homographies = plane_homographies(every, used.matrix(), reference, normal, distance)
            save_level(store, LevelState(level, levels, exposures, homographies, landmarks, used, current, final,
                                         self._database), work_dir)
        frames, poses = exposures[-1]
        assert final is not None  # level 1's model at least (or it raised)
        model_dir = work_dir / "model"
        model_dir.mkdir(exist_ok=True)
        final.write(str(model_dir))
        xyz = np.array([p.xyz for p in final.points3D.values()], np.float64).reshape(-1, 3)
        rgb = np.array([p.color for p in final.points3D.values()], np.uint8).reshape(-1, 3)
        return PoseResult(
            poses=interpolate_poses(frames, poses, n),
            exposure_frames=frames,
            exposure_poses=poses,
            points=xyz,
            colors=rgb,
            intrinsics=used,
            levels=levels,
            level_exposures=exposures,
            model_dir=model_dir,
        )

    def _refine(
        self,
        images: NDArray[np.uint8],
        references: NDArray[np.int64],
        poses: NDArray[np.float64],
        rec: Any,
        folder: Path,
        progress: Any,
        level: int,
    ) -> tuple[NDArray[np.float64], Any, dict[str, float]]:
        """Triangulate the level's exposures from their registered poses, then bundle-adjust poses and points.

        The camera is that of ``rec`` (fixed, or refined when self-calibrating with
        ``refine_intrinsics``). Exposures that failed to register
        keep NaN poses. With ``track_window`` set, every track's keypoints are then re-located
        by patch alignment (:func:`refine_tracks`), the model bundle-adjusted again, and
        with ``track_prune`` the outlying observations dropped before a last adjustment.

        Returns:
            ``(poses, reconstruction, stats)``: refined (G, 4, 4) camera-to-world poses, the
            model and the track refinement's figures (empty without it).
        """
        import pycolmap

        camera = next(iter(rec.cameras.values()))
        database, image_dir = write_and_match(
            self.config,
            images,
            references,
            folder,
            camera.model.name,
            [float(v) for v in camera.params],
            progress,
            level,
            seed=self.config.seed,
        )
        model = pycolmap.Reconstruction()
        db = pycolmap.Database.open(str(database))
        try:
            db_camera = db.read_all_cameras()[0]
            fixed = pycolmap.Camera(
                model=camera.model.name,
                width=camera.width,
                height=camera.height,
                params=camera.params,
                camera_id=db_camera.camera_id,
            )
            model.add_camera_with_trivial_rig(fixed)
            for image in db.read_all_images():
                index = int(np.searchsorted(references, int(Path(image.name).stem)))
                if not np.isfinite(poses[index, 0, 0]):
                    continue
                keypoints = np.asarray(db.read_keypoints(image.image_id))[:, :2]
                entry = pycolmap.Image(
                    name=image.name,
                    keypoints=keypoints.astype(np.float64),
                    camera_id=db_camera.camera_id,
                    image_id=image.image_id,
                )
                world_from_cam = poses[index]
                cam_from_world = pycolmap.Rigid3d(
                    pycolmap.Rotation3d(world_from_cam[:3, :3].T),
                    -world_from_cam[:3, :3].T @ world_from_cam[:3, 3],
                )
                model.add_image_with_trivial_frame(entry, cam_from_world)
        finally:
            db.close()
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = THREADS
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        (folder / "sparse").mkdir(exist_ok=True)
        model = pycolmap.triangulate_points(
            model,
            database,
            image_dir,
            folder / "sparse",
            clear_points=True,
            options=options,
            refine_intrinsics=False,
        )
        adjust = pycolmap.BundleAdjustmentOptions()
        adjust.refine_focal_length = self._calibrate
        adjust.refine_principal_point = False
        adjust.refine_extra_params = self._calibrate
        adjust.print_summary = False
        adjust.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        pycolmap.bundle_adjustment(model, adjust)
        stats: dict[str, float] = {}
        if self.config.track_window:
            exposures = {
                image_id: images[int(np.searchsorted(references, int(Path(image.name).stem)))]
                for image_id, image in model.images.items()
            }
            stats = refine_tracks(model, exposures, self.config.track_window, self.config.track_max_shift_px)
            pycolmap.bundle_adjustment(model, adjust)
            if self.config.track_prune:
                stats.update(prune_observations(model, self.config.track_prune))
                pycolmap.bundle_adjustment(model, adjust)
        model.extract_colors_for_all_images(str(image_dir))
        self._database = database
        return model_poses(model, references), model, stats

    def _check_light(self, source: PhotonSource, merged: Any) -> None:
        """Raise StageError if the level-1 exposures hold too few photons to register."""
        photons = float(np.nanmean(merged.flux)) * source.exposure_s * self.config.group_size
        if not np.isfinite(photons) or photons < self.config.min_photons:
            raise StageError(
                "pose_estimator",
                "pycolmap-sfm",
                f"the capture is too dark: {photons:.2f} photons per "
                f"pixel per virtual exposure of {self.config.group_size} frames (at least "
                f"{self.config.min_photons} needed; raise group_size)",
            )

@hookimpl
def photonpano_register_pose_estimators() -> list[type[PoseEstimatorConfig]]:
    """Register the ``pycolmap-sfm`` pose estimator."""
    return [PycolmapSfMConfig]
