"""Experimental 6-DoF pose estimation: records, SE(3) interpolation, metrics, plane homographies.

Poses are camera-to-world 4x4 float64 matrices ``P = [[R, c], [0, 1]]`` in OpenCV camera
axes (x right, y down, z forward): a point ``X_cam`` in the camera maps to
``R @ X_cam + c`` in the world, and ``c`` is the camera centre. Intrinsics follow
OpenCV (pixel centres at integer coordinates); COLMAP puts them at +0.5.

Metrics (Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS
2012): the absolute trajectory error (ATE) is the RMS distance between estimated and
true camera centres after the similarity transform that best aligns them (Umeyama,
"Least-squares estimation of transformation parameters between two point patterns",
PAMI 1991); the relative pose error (RPE) compares the motion between frames ``i`` and
``i + gap`` in the estimate (after the same alignment) with the true one, reported in
metres and as a percentage of the true motion over that gap.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import SpecError

__all__ = [
    "Intrinsics",
    "PoseResult",
    "interpolate_poses",
    "umeyama",
    "align_to",
    "absolute_trajectory_error",
    "relative_pose_error",
    "plane_homographies",
    "dominant_plane",
]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, OpenCV convention (pixel centres at integers).

    Attributes:
        fx: focal length along x, pixels.
        fy: focal length along y, pixels.
        cx: principal point x, pixels (0 = centre of the first column).
        cy: principal point y, pixels (0 = centre of the first row).
    """

    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> NDArray[np.float64]:
        """Return the (3, 3) float64 camera matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float64)

    def colmap_params(self) -> list[float]:
        """Return COLMAP ``PINHOLE`` parameters ``[fx, fy, cx + 0.5, cy + 0.5]``."""
        return [self.fx, self.fy, self.cx + 0.5, self.cy + 0.5]

    def as_dict(self) -> dict[str, float]:
        """Return ``{"fx", "fy", "cx", "cy"}`` as plain floats (the intrinsics file format)."""
        return {"fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy)}

    @classmethod
    def load(cls, path: Path) -> Intrinsics:
        """Read a JSON file with at least ``fx``, ``fy``, ``cx``, ``cy`` (pixels; other keys ignored).

        Raises:
            SpecError: missing or unreadable file, not JSON, a missing key, or a value that
                is not a finite number (focal lengths must be positive).
        """
        try:
            data = json.loads(Path(path).read_text())
        except OSError as exc:
            raise SpecError(f"intrinsics {path}: cannot read: {exc.strerror or exc}") from None
        except ValueError as exc:
            raise SpecError(f"intrinsics {path}: not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise SpecError(f"intrinsics {path}: expected a JSON object with fx, fy, cx, cy (pixels)")
        values = {}
        for key in ("fx", "fy", "cx", "cy"):
            value = data.get(key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise SpecError(
                    f"intrinsics {path}: '{key}' must be a finite number of pixels, got {value!r}"
                )
            values[key] = float(value)
        if values["fx"] <= 0 or values["fy"] <= 0:
            raise SpecError(f"intrinsics {path}: fx and fy must be positive (pixels)")
        return cls(**values)


@dataclass(frozen=True)
class PoseResult:
    """What a pose estimator found.

    Attributes:
        poses: (T, 4, 4) float64 camera-to-world pose of every binary frame (NaN rows
            for frames without one), OpenCV axes, in the model's world frame and scale.
        exposure_frames: (E,) int64 centre (reference) frame of each virtual exposure
            of the final level.
        exposure_poses: (E, 4, 4) float64 their poses (NaN where not registered).
        points: (N, 3) float64 sparse scene points (world frame).
        colors: (N, 3) uint8 their grey-level colours (RGB).
        intrinsics: the intrinsics used (given, or estimated by self-calibration).
        levels: one JSON-ready dict per level (exposures, registered, points, mean
            reprojection error in pixels, timings in seconds).
        level_exposures: per level, ``(exposure_frames, exposure_poses)`` as above.
        model_dir: folder of the final level's COLMAP model, or None.
    """

    poses: NDArray[np.float64]
    exposure_frames: NDArray[np.int64]
    exposure_poses: NDArray[np.float64]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8]
    intrinsics: Intrinsics
    levels: list[dict[str, Any]] = field(default_factory=list)
    level_exposures: list[tuple[NDArray[np.int64], NDArray[np.float64]]] = field(default_factory=list)
    model_dir: Path | None = None


# --- SE(3) interpolation ----------------------------------------------------------------


def interpolate_poses(
    frames: NDArray[np.int64], poses: NDArray[np.float64], n_frames: int
) -> NDArray[np.float64]:
    """Interpolate camera-to-world poses known at some frames to every binary frame.

    Rotations are interpolated by piecewise slerp, camera centres by a cubic spline
    (not-a-knot ends). Before the first and after the last known frame the rotation
    continues at the angular velocity of the nearest segment and the centre follows the
    spline's end cubic, so the ends neither freeze nor jump.

    Args:
        frames: (K,) int64 frame indices of the known poses (any order; rows with NaN
            poses are ignored).
        poses: (K, 4, 4) float64 camera-to-world poses.
        n_frames: number of binary frames T.

    Returns:
        (T, 4, 4) float64 poses; all NaN if no pose is known, constant if one is.
    """
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, Slerp

    frames = np.asarray(frames, np.int64)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    ok = np.all(np.isfinite(poses), axis=(1, 2))
    frames, poses = frames[ok], poses[ok]
    order = np.argsort(frames)
    frames, poses = frames[order], poses[order]
    frames, unique = np.unique(frames, return_index=True)
    poses = poses[unique]
    out = np.full((n_frames, 4, 4), np.nan)
    if len(frames) == 0:
        return out
    if len(frames) == 1:
        out[:] = poses[0]
        return out
    t = np.arange(n_frames, dtype=np.float64)
    rots = Rotation.from_matrix(poses[:, :3, :3])
    inside = (t >= frames[0]) & (t <= frames[-1])
    r = np.empty((n_frames, 3, 3))
    r[inside] = Slerp(frames.astype(np.float64), rots)(t[inside]).as_matrix()
    for end, (a, b) in ((t < frames[0], (0, 1)), (t > frames[-1], (-2, -1))):
        if end.any():
            rate = (rots[a].inv() * rots[b]).as_rotvec() / float(frames[b] - frames[a])
            anchor = rots[0] if a == 0 else rots[-1]
            base = frames[0] if a == 0 else frames[-1]
            r[end] = (anchor * Rotation.from_rotvec(np.outer(t[end] - base, rate))).as_matrix()
    # not-a-knot: the end pieces are the cubics through the last four keyframes, which also
    # extrapolate the (half-group) ends
    spline = CubicSpline(frames.astype(np.float64), poses[:, :3, 3], bc_type="not-a-knot")
    out[:, :3, :3], out[:, :3, 3] = r, spline(t)
    out[:, 3] = (0, 0, 0, 1)
    return out


# --- metrics --------------------------------------------------------------------------------


def umeyama(
    source: NDArray[np.float64], target: NDArray[np.float64], *, with_scale: bool = True
) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares similarity ``target ~ s R source + t`` (Umeyama 1991, Eqs. 40-42).

    Args:
        source: (N, 3) float64 points, N >= 3 not collinear.
        target: (N, 3) float64 corresponding points.
        with_scale: estimate the scale s (else s = 1).

    Returns:
        ``(s, R, t)``: scale, (3, 3) rotation, (3,) translation.

    Raises:
        ValueError: fewer than 3 points or degenerate (coincident) points.
    """
    if len(source) < 3:
        raise ValueError("umeyama: at least 3 points are needed")
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    var_s = float((xs**2).sum() / len(source))
    if var_s <= 0:
        raise ValueError("umeyama: the source points coincide")
    u, d, vt = np.linalg.svd(xt.T @ xs / len(source))
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rot = u @ sign @ vt
    s = float(np.trace(np.diag(d) @ sign) / var_s) if with_scale else 1.0
    return s, rot, mu_t - s * rot @ mu_s


def align_to(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> NDArray[np.float64]:
    """Apply the similarity that best maps the estimated camera centres onto the true ones.

    Args:
        estimate: (T, 4, 4) float64 camera-to-world poses (NaN rows allowed).
        truth: (T, 4, 4) float64 true poses.

    Returns:
        (T, 4, 4) float64 aligned poses: rotations rotated, centres mapped ``s R c + t``.
    """
    ok = np.all(np.isfinite(estimate.reshape(len(estimate), -1)), axis=1)
    s, rot, t = umeyama(estimate[ok, :3, 3], truth[ok, :3, 3])
    out = estimate.copy()
    out[:, :3, :3] = rot @ estimate[:, :3, :3]
    out[:, :3, 3] = s * estimate[:, :3, 3] @ rot.T + t
    return out


def absolute_trajectory_error(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """RMS camera-centre error (world units of ``truth``, e.g. metres) after similarity alignment.

    Args:
        estimate: (T, 4, 4) float64 poses (NaN rows are skipped).
        truth: (T, 4, 4) float64 true poses.
    """
    aligned = align_to(estimate, truth)
    ok = np.all(np.isfinite(aligned[:, :3, 3]), axis=1)
    return float(np.sqrt(np.mean(np.sum((aligned[ok, :3, 3] - truth[ok, :3, 3]) ** 2, axis=1))))


def relative_pose_error(
    estimate: NDArray[np.float64], truth: NDArray[np.float64], gap: int, stride: int = 10
) -> dict[str, float]:
    """Relative pose error over ``gap`` frames, after similarity alignment.

    For frame pairs ``(i, i + gap)`` (every ``stride``-th i with both poses known), the
    relative motion ``inv(P_i) @ P_{i+gap}`` of the estimate is compared with the true one.

    Args:
        estimate: (T, 4, 4) float64 poses (NaN rows allowed).
        truth: (T, 4, 4) float64 true poses.
        gap: frame gap (frames).
        stride: spacing of the first frames of the pairs (frames).

    Returns:
        ``translation_m`` (RMS translation error), ``motion_m`` (RMS true translation),
        ``percent`` (100 * their ratio), ``rotation_deg`` (RMS rotation error).

    Raises:
        ValueError: if no pair has both poses.
    """
    aligned = align_to(estimate, truth)
    i = np.arange(0, len(truth) - gap, stride)
    ok = np.all(np.isfinite(aligned[i].reshape(len(i), -1)), axis=1) & np.all(
        np.isfinite(aligned[i + gap].reshape(len(i), -1)), axis=1
    )
    i = i[ok]
    if len(i) == 0:
        raise ValueError(f"relative_pose_error: no frame pair {gap} frames apart has both poses")
    rel_e = np.linalg.inv(aligned[i]) @ aligned[i + gap]
    rel_t = np.linalg.inv(truth[i]) @ truth[i + gap]
    err = np.linalg.inv(rel_t) @ rel_e
    trans = np.sqrt(np.mean(np.sum(err[:, :3, 3] ** 2, axis=1)))
    motion = np.sqrt(np.mean(np.sum(rel_t[:, :3, 3] ** 2, axis=1)))
    cos = np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
    rot = np.degrees(np.sqrt(np.mean(np.arccos(cos) ** 2)))
    return {
        "translation_m": float(trans),
        "motion_m": float(motion),
        "percent": float(100 * trans / max(motion, 1e-12)),
        "rotation_deg": float(rot),
    }


# --- motion-compensated merging ---------------------------------------------------------------


def dominant_plane(points: NDArray[np.float64], reference: NDArray[np.float64]) -> tuple[NDArray, float]:
    """A fronto-parallel plane at the median depth of the scene points seen from ``reference``.

    Args:
        points: (N, 3) float64 world points, N >= 1.
        reference: (4, 4) float64 camera-to-world pose of the reference camera.

    Returns:
        ``(normal, distance)`` in the reference camera's axes: the plane ``n . X = d``
        with ``n = (0, 0, 1)`` and ``d`` the median positive depth (world units).

    Raises:
        ValueError: if no point lies in front of the reference camera.
    """
    cam = (points - reference[:3, 3]) @ reference[:3, :3]
    depth = cam[:, 2][cam[:, 2] > 0]
    if len(depth) == 0:
        raise ValueError("dominant_plane: no scene point lies in front of the reference camera")
    return np.array([0.0, 0.0, 1.0]), float(np.median(depth))


def plane_homographies(
    poses: NDArray[np.float64],
    k: NDArray[np.float64],
    reference: NDArray[np.float64],
    normal: NDArray[np.float64],
    distance: float,
) -> NDArray[np.float64]:
    """Plane-induced homographies from each frame's pixels to a reference camera's pixels.

    With ``Q_t = inv(P_ref) @ P_t = [[R, c], [0, 1]]`` (frame t in the reference camera's
    axes) and the plane ``n . X = d`` in those axes, ``H_t = K (R + c n_t^T / d_t) K^-1``
    with ``n_t = R^T n`` and ``d_t = d - n . c`` (Hartley & Zisserman, Eq. 13.2). These are
    the frame-to-"panorama" homographies the mergers take; scale-free (``c / d``).

    Args:
        poses: (T, 4, 4) float64 camera-to-world poses (no NaN).
        k: (3, 3) float64 camera matrix (OpenCV convention).
        reference: (4, 4) float64 camera-to-world pose of the reference camera.
        normal: (3,) float64 unit plane normal in the reference camera's axes.
        distance: plane distance d from the reference camera (world units, > 0).

    Returns:
        (T, 3, 3) float64 homographies, ``H[2, 2] == 1``.
    """
    q = np.linalg.inv(reference) @ poses
    rot, c = q[:, :3, :3], q[:, :3, 3]
    n_t = np.einsum("tji,j->ti", rot, normal)
    d_t = distance - c @ normal
    h = k @ (rot + c[:, :, None] * n_t[:, None, :] / d_t[:, None, None]) @ np.linalg.inv(k)
    return h / h[:, 2:3, 2:3]
