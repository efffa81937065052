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

__all__ = ["pose_report", "write_ply", "run_pose"]


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


def _copy_model(model_dir: Path, out_dir: Path) -> None:
    """Copy the reconstruction's files into ``out_dir/model``, each atomically and never through a link."""
    import shutil

    from .outputs.files import atomic_path, inside, oserror

    for source in sorted(Path(model_dir).rglob("*")):
        if not source.is_file() or source.is_symlink():
            continue
        name = f"model/{source.relative_to(model_dir).as_posix()}"
        target = inside(out_dir, name)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            inside(out_dir, name)
            with atomic_path(target) as tmp:
                shutil.copyfile(source, tmp)
        except OSError as exc:
            raise oserror(target, exc) from None


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


def run_pose(
    spec: Any,
    out_dir: Path | None,
    host: Any,
    *,
    intrinsics: Intrinsics | None = None,
    force: bool = False,
    rpe_gap: int | None = None,
) -> tuple[dict[str, Any], PoseResult]:
    """Run a spec's ``pose_estimator`` on its source and write the pose outputs.

    Outputs in ``out_dir``: ``poses.npy`` (T, 4, 4), ``exposure_poses.npy`` (E, 4, 4),
    ``exposure_frames.npy`` (E,), ``points.ply``, ``model/`` (COLMAP model),
    ``intrinsics.json``, ``trajectory.png``, ``spec.yaml`` and, last, ``run.json``.

    Args:
        spec: a validated ``PipelineSpec`` whose ``pose_estimator`` is set.
        out_dir: output folder (must be empty unless ``force``), or None for a run in a
            temporary folder whose files are discarded.
        host: the plugin host (progress goes to its hooks).
        intrinsics: known intrinsics; None: those in the file ``pose_estimator.intrinsics``,
            or self-calibration if it names none.
        force: allow writing into a non-empty folder.
        rpe_gap: frame gap of the relative pose error (default: the group size m).

    Returns:
        ``(summary, result)``: the ``run.json`` content and the :class:`PoseResult`.

    Raises:
        PhotonpanoError: bad output folder, unreadable source, failed estimation.
    """
    import shutil
    import tempfile

    from .outputs import atomic_path, save_npy, write_text
    from .outputs.files import inside, refuse_symlink
    from .pipeline import prepare_output
    from .progress import reporting, start_task
    from .provenance import run_header
    from .spec import dump_spec

    if out_dir is not None:
        refuse_symlink(out_dir, "output folder")  # never written through, --force or not
    if getattr(spec, "pose_estimator", None) is None:
        raise SpecError("spec: no pose_estimator section (e.g. pose_estimator: pycolmap-sfm)")
    type(spec.source).check_available()
    type(spec.pose_estimator).check_available()
    if intrinsics is None and spec.pose_estimator.intrinsics is not None:
        intrinsics = Intrinsics.load(spec.pose_estimator.intrinsics)
    if out_dir is not None:
        prepare_output(out_dir, force)
        write_text(inside(out_dir, "spec.yaml"), dump_spec(spec))
    if out_dir is None:
        work = Path(tempfile.mkdtemp(prefix="photonpano-pose-"))
    else:
        work = inside(out_dir, "work", folder=True)
    timings: dict[str, float] = {}
    try:
        with reporting(host):
            t0 = time.perf_counter()
            source = spec.source.build()
            timings["source"] = time.perf_counter() - t0
            if getattr(source, "kind", "binary") != "binary":
                raise StageError(
                    "pose_estimator",
                    type(spec.pose_estimator).__name__,
                    f"source {source.name!r} is not a binary capture",
                )
            work.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            result = spec.pose_estimator.build().estimate(source, intrinsics, work, progress=start_task)
            timings["estimate"] = time.perf_counter() - t0
        summary: dict[str, Any] = {
            **run_header(spec, host, source),
            "intrinsics": {
                "given": intrinsics.as_dict() if intrinsics else None,
                "used": result.intrinsics.as_dict(),
            },
            "frames_with_pose": int(
                np.all(np.isfinite(result.poses.reshape(len(result.poses), -1)), axis=1).sum()
            ),
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
        if out_dir is not None:  # atomic files, never through a link (run.json last)
            save_npy(inside(out_dir, "poses.npy"), result.poses)
            save_npy(inside(out_dir, "exposure_poses.npy"), result.exposure_poses)
            save_npy(inside(out_dir, "exposure_frames.npy"), result.exposure_frames)
            with atomic_path(inside(out_dir, "points.ply")) as tmp:
                write_ply(tmp, result.points, result.colors)
            if result.model_dir is not None:
                _copy_model(result.model_dir, out_dir)
            write_text(inside(out_dir, "intrinsics.json"), json.dumps(result.intrinsics.as_dict(), indent=2))
            with atomic_path(inside(out_dir, "trajectory.png")) as tmp:
                _plot(tmp, result, truth)
            write_text(inside(out_dir, "run.json"), json.dumps(summary, indent=2))
        return summary, result
    finally:
        if out_dir is None:
            shutil.rmtree(work, ignore_errors=True)
