"""The ``photonpano pose`` run: build the source and pose estimator, score, write the outputs.

See :mod:`photonpano.pose` for the pose conventions and metrics and ``docs/pose.md`` for the
outputs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import SpecError, StageError
from .pose import (
    Intrinsics,
    PoseResult,
    absolute_trajectory_error,
    align_to,
    interpolate_poses,
    relative_pose_error,
)

__all__ = ["pose_report", "write_ply", "PoseStages", "level_warnings", "run_pose"]


def pose_report(result: PoseResult, truth: NDArray[np.float64], gap: int) -> list[dict[str, Any]]:
    """Score every level of ``result`` against true poses.

    Args:
        result: the estimator's result.
        truth: (T, 4, 4) float64 true camera-to-world poses.
        gap: frame gap of the relative pose error (frames).

    Returns:
        One dict per level: ``ate_m``, ``rpe`` (see :func:`relative_pose_error`),
        ``exposure_ate_m`` (ATE at the registered exposures' centre frames only).
    """
    rows = []
    for frames, poses in result.level_exposures:
        row: dict[str, Any] = {}
        ok = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
        if ok.sum() >= 3:
            every = interpolate_poses(frames, poses, len(truth))
            row["ate_m"] = absolute_trajectory_error(every, truth)
            row["exposure_ate_m"] = absolute_trajectory_error(poses[ok], truth[frames[ok]])
            row["rpe"] = relative_pose_error(every, truth, gap)
        rows.append(row)
    return rows


def write_ply(path: Path, points: NDArray[np.float64], colors: NDArray[np.uint8]) -> None:
    """Write points with colours as a binary little-endian PLY.

    Args:
        path: output file.
        points: (N, 3) float64 positions.
        colors: (N, 3) uint8 RGB colours.
    """
    record = np.empty(
        len(points),
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    for i, name in enumerate("xyz"):
        record[name] = points[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        record[name] = colors[:, i]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(record.tobytes())


def _copy_model(model_dir: Path, folder: Any) -> None:
    """Copy the reconstruction's files into ``model/`` of ``folder`` (a RunFolder), each atomically."""
    import shutil

    for source in sorted(Path(model_dir).rglob("*")):
        if source.is_file() and not source.is_symlink():
            folder.write_with(f"model/{source.relative_to(model_dir).as_posix()}",
                              lambda tmp, source=source: shutil.copyfile(source, tmp))


def _plot(path: Path, result: PoseResult, truth: NDArray[np.float64] | None) -> None:
    """Top view (x, z), x/y/z over time and, with ground truth, the error over time of the trajectory."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poses = result.poses
    if truth is not None:
        poses = align_to(poses, truth)
    fig, axes = plt.subplots(1, 3 if truth is not None else 2, figsize=(16 if truth is not None else 11, 4.5))
    top, time_ax = axes[:2]
    if truth is not None:
        top.plot(truth[:, 0, 3], truth[:, 2, 3], "k-", lw=1, label="true")
    top.plot(
        poses[:, 0, 3],
        poses[:, 2, 3],
        "-",
        lw=1,
        label="estimate" + (" (aligned)" if truth is not None else ""),
    )
    top.set(xlabel="x (world)", ylabel="z (world)", title="camera centres, top view", aspect="equal")
    top.legend()
    t = np.arange(len(poses))
    for axis, name in enumerate("xyz"):
        time_ax.plot(t, poses[:, axis, 3], lw=1, label=f"{name} estimate")
        if truth is not None:
            time_ax.plot(t, truth[:, axis, 3], "k:", lw=0.8)
    time_ax.set(xlabel="binary frame", ylabel="camera centre (world)", title="camera centre over time")
    time_ax.legend(fontsize=8)
    if truth is not None:
        error = 1e3 * (poses[:, :3, 3] - truth[:, :3, 3])
        for axis, name in enumerate("xyz"):
            axes[2].plot(t, error[:, axis], lw=0.8, label=name)
        axes[2].set(xlabel="binary frame", ylabel="error (truth units / 1000)", title="centre error, aligned")
        axes[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


class PoseStages:
    """The stages of a pose spec, built once for one opened capture.

    The pose counterpart of :class:`photonpano.pipeline.Stages`.

    Args:
        spec: a validated ``PipelineSpec`` whose ``pose_estimator`` is set.
        source: the opened capture; it must hold binary frames.

    Raises:
        StageError: the source is not a binary capture (a high-speed video, say).
    """

    def __init__(self, spec: Any, source: Any) -> None:
        """Build the pose estimator of ``spec`` for ``source``."""
        if getattr(source, "kind", "binary") != "binary":
            raise StageError("pose_estimator", type(spec.pose_estimator).__name__,
                             f"source {source.name!r} is not a binary capture")
        self.spec, self.source = spec, source
        self.estimator = spec.pose_estimator.build()

    def estimate(self, intrinsics: Intrinsics | None, work_dir: Path, checkpoints: Any = None) -> PoseResult:
        """Run the estimator on the capture.

        Args:
            intrinsics: known intrinsics, or None for self-calibration.
            work_dir: a folder for the estimator's intermediate files (created).
            checkpoints: a :class:`~photonpano.pose_checkpoints.PoseCheckpoints` for an
                estimator whose ``estimate`` takes ``checkpoints`` (``pycolmap-sfm``):
                it saves each level there and resumes after the latest; None: no checkpoints.

        Returns:
            The estimator's :class:`PoseResult`.
        """
        import inspect

        from .progress import start_task

        work_dir.mkdir(parents=True, exist_ok=True)
        extra = {"checkpoints": checkpoints} if checkpoints is not None and "checkpoints" in inspect.signature(
            self.estimator.estimate).parameters else {}
        return self.estimator.estimate(self.source, intrinsics, work_dir, progress=start_task, **extra)


def level_warnings(levels: list[dict[str, Any]]) -> list[str]:
    """One line for each level that ended worse than the level before it.

    A level >= 2 is worse by its own figures when it registered a smaller fraction of its
    exposures (by more than :data:`REGISTERED_DROP`), when its mean reprojection error is
    larger (by the factor :data:`REPROJECTION_RISE`, and above
    :data:`REPROJECTION_FLOOR_PX`), or when it stopped early and kept
    the previous level's poses (its ``note``); with ground truth scored into the rows
    (``ate_m``), also when its ATE is larger than the previous level's by more than
    :data:`ATE_RISE`.

    Args:
        levels: the ``run.json`` rows of a pose run (``level``, ``exposures``,
            ``registered``, optional ``reprojection_error_px``, ``note``, ``ate_m``).

    Returns:
        The warnings, in level order (empty when every level improved or held).
    """
    warnings = []
    for before, row in zip(levels, levels[1:]):
        level, previous = row["level"], before["level"]
        if row.get("note"):
            warnings.append(f"level {level}: {row['note']}")
            continue
        reasons = []
        was = before["registered"] / max(before["exposures"], 1)
        now = row["registered"] / max(row["exposures"], 1)
        if now < was - REGISTERED_DROP:
            reasons.append(f"registered {row['registered']} of {row['exposures']} exposures "
                           f"({100 * now:.0f} % against {100 * was:.0f} % at level {previous})")
        error, error_before = row.get("reprojection_error_px"), before.get("reprojection_error_px")
        if (error is not None and error_before is not None and error > error_before * REPROJECTION_RISE
                and error > REPROJECTION_FLOOR_PX):
            reasons.append(f"mean reprojection error {error:.2f} px against {error_before:.2f} px")
        ate, ate_before = row.get("ate_m"), before.get("ate_m")
        if ate is not None and ate_before is not None and ate > ate_before * ATE_RISE:
            reasons.append(f"ATE against the ground truth {1e3 * ate:.2f} mm against {1e3 * ate_before:.2f} mm")
        if reasons:
            warnings.append(f"level {level} ended worse than level {previous}: " + "; ".join(reasons))
    return warnings


REGISTERED_DROP = 0.25
"""Fraction of exposures registered: a later level with this much less warns."""
REPROJECTION_RISE = 1.5
"""Mean reprojection error: a later level with this factor more warns (above :data:`REPROJECTION_FLOOR_PX`)."""
REPROJECTION_FLOOR_PX = 0.5
"""Mean reprojection errors below this many pixels never warn (levels >= 2 refine their
keypoints to a tenth of a pixel; from so low a figure, a rise is noise)."""
ATE_RISE = 1.2
"""ATE against the ground truth: a later level with this factor more warns."""


def run_pose(
    spec: Any,
    out_dir: Path | None,
    host: Any,
    *,
    intrinsics: Intrinsics | None = None,
    force: bool = False,
    rpe_gap: int | None = None,
    resume: bool = False,
) -> tuple[dict[str, Any], PoseResult]:
    """Run a spec's ``pose_estimator`` on its source and write the pose outputs.

    Outputs in ``out_dir``, written through a :class:`~photonpano.outputs.RunFolder` like
    ``run``'s (atomic files, a manifest with hashes, a lock; a failed run removes what it
    wrote): ``poses.npy`` (T, 4, 4), ``exposure_poses.npy`` (E, 4, 4),
    ``exposure_frames.npy`` (E,), ``points.ply``, ``model/`` (COLMAP model),
    ``intrinsics.json``, ``trajectory.png``, ``spec.yaml``, ``work/`` (the estimator's
    intermediate files) and, last, ``run.json`` (with ``status`` and ``warnings``: see
    :func:`level_warnings`).

    Args:
        spec: a validated ``PipelineSpec`` whose ``pose_estimator`` is set.
        out_dir: output folder (must be empty unless ``force``), or None for a run in a
            temporary folder whose files are discarded.
        host: the plugin host (progress goes to its hooks).
        intrinsics: known intrinsics; None: those in the file ``pose_estimator.intrinsics``,
            or self-calibration if it names none.
        force: replace the previous run's outputs (the files its manifest lists).
        rpe_gap: frame gap of the relative pose error (default: the group size m).
        resume: continue the interrupted run in ``out_dir`` (same spec) after its last
            checkpointed level (:mod:`photonpano.pose_checkpoints`): those levels' results
            are reused bit for bit, the later ones estimated again.

    Returns:
        ``(summary, result)``: the ``run.json`` content and the :class:`PoseResult`.

    Raises:
        PhotonpanoError: bad output folder, unreadable source, failed estimation.
    """
    import tempfile

    from .outputs import RunFolder
    from .outputs.files import refuse_symlink
    from .pipeline import _input_paths
    from .progress import reporting
    from .spec import check_available

    if force and resume:
        raise SpecError("pose: --force and --resume exclude each other")
    if out_dir is not None:
        refuse_symlink(out_dir, "output folder")  # never written through, --force or not
    if getattr(spec, "pose_estimator", None) is None:
        raise SpecError("spec: no pose_estimator section (e.g. pose_estimator: pycolmap-sfm)")
    check_available(spec)
    if intrinsics is None and spec.pose_estimator.intrinsics is not None:
        intrinsics = Intrinsics.load(spec.pose_estimator.intrinsics)
    with reporting(host):
        if out_dir is None:
            with tempfile.TemporaryDirectory(prefix="photonpano-pose-") as work:
                return _pose_into(spec, None, Path(work), host, intrinsics, rpe_gap)
        with RunFolder(out_dir, force=force, resume=resume, inputs=_input_paths(spec)) as folder:
            return _pose_into(spec, folder, None, host, intrinsics, rpe_gap)


def _pose_into(spec: Any, folder: Any, work: Path | None, host: Any, intrinsics: Intrinsics | None,
               rpe_gap: int | None) -> tuple[dict[str, Any], PoseResult]:
    """Run the pose stages, writing into ``folder`` (a RunFolder) unless it is None (then into ``work``)."""
    import logging

    from .outputs.files import inside
    from .provenance import run_header
    from .spec import dump_spec

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    source = spec.source.build()
    timings["source"] = time.perf_counter() - t0
    stages = PoseStages(spec, source)
    checkpoints = None
    if folder is not None:
        from .pipeline import _resume_state
        from .pose_checkpoints import PoseCheckpoints

        spec_text = dump_spec(spec)
        if folder.resume:
            _resume_state(folder, spec_text)  # the same spec as the interrupted run's, or one line
        folder.begin()  # the spec is valid and the source open: the folder gets its first files
        folder.write_text("spec.yaml", spec_text)
        work = inside(folder.root, "work", folder=True)
        checkpoints = PoseCheckpoints(folder)
    assert work is not None  # a temporary folder when there is no run folder
    t0 = time.perf_counter()
    try:
        result = stages.estimate(intrinsics, work, checkpoints)
    except BaseException:
        if folder is not None and work.is_dir() and not any(work.iterdir()):
            work.rmdir()  # the run folder removes the files it lists, not an empty folder
        raise
    timings["estimate"] = time.perf_counter() - t0
    summary: dict[str, Any] = {
        **run_header(spec, host, source),
        "intrinsics": {"given": intrinsics.as_dict() if intrinsics else None, "used": result.intrinsics.as_dict()},
        "frames_with_pose": int(np.all(np.isfinite(result.poses.reshape(len(result.poses), -1)), axis=1).sum()),
        "levels": result.levels,
        "timings_s": timings,
    }
    truth = getattr(source, "ground_truth_poses", None)
    if truth is not None:
        gap = rpe_gap or int(getattr(spec.pose_estimator, "group_size", 1000))
        report = pose_report(result, truth, gap)
        for row, scores in zip(summary["levels"], report):
            row.update(scores)
        summary["ground_truth"] = {"rpe_gap_frames": gap, **report[-1]}
    warnings = level_warnings(summary["levels"])
    for line in warnings:
        logging.getLogger("photonpano").debug("pose: %s", line)
    summary["status"], summary["warnings"] = ("degraded" if warnings else "ok"), warnings
    if folder is not None:  # atomic files, never through a link, in the manifest (run.json last)
        folder.save_npy("poses.npy", result.poses)
        folder.save_npy("exposure_poses.npy", result.exposure_poses)
        folder.save_npy("exposure_frames.npy", result.exposure_frames)
        folder.write_with("points.ply", lambda tmp: write_ply(tmp, result.points, result.colors))
        if result.model_dir is not None:
            _copy_model(result.model_dir, folder)
        folder.write_text("intrinsics.json", json.dumps(result.intrinsics.as_dict(), indent=2))
        folder.write_with("trajectory.png", lambda tmp: _plot(tmp, result, truth))
        folder.commit(json.dumps(summary, indent=2))
    return summary, result
