"""Source ``simulate3d``: a SPAD capture of a piecewise-planar room with a 6-DoF camera path.

The room is a few textured rectangles at different depths (a back wall, a floor, a side
wall and two free-standing panels), their textures cut from real photographs (the
bundled photo by default). Each binary frame is rendered exactly through plane-induced
homographies (texture pixels -> frame pixels, ``H = K R^T [u s | v s | p0 - c]``),
nearer planes painted over farther ones, then photons are drawn with Eq. (2) of the paper
as in ``simulate``. Ground truth: camera-to-world poses (OpenCV axes: x right, y down,
z forward; metres) and the intrinsics.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.plugins.sources.simulate import bundled_photo, load_scene
from photonpano.stages import PhotonSource, SourceConfig
from pydantic import Field

#: The room: (origin p0, in-plane axes u and v, size along u and v in metres, depth at which one
#: texture pixel covers one frame pixel). Listed far to near (painting order).
ROOM_PLANES = (
    ((-2.9, -1.6, 4.0), (1, 0, 0), (0, 1, 0), (5.8, 2.6), 4.0),  # back wall
    ((-2.9, 0.8, 1.2), (1, 0, 0), (0, 0, 1), (5.8, 2.8), 3.0),  # floor
    ((-1.6, -1.6, 1.2), (0, 0, 1), (0, 1, 0), (2.8, 2.4), 3.0),  # left wall
    ((0.35, -0.55, 2.8), (1, 0, 0), (0, 1, 0), (1.1, 0.9), 2.8),  # panel, right
    ((-1.05, -0.25, 2.0), (1, 0, 0), (0, 1, 0), (0.8, 0.65), 2.0),  # panel, left, nearest
)


class Simulate3DConfig(SourceConfig):
    """Simulate binary frames of a camera moving (6-DoF) through a textured, piecewise-planar room."""

    plugin: Literal["simulate3d"] = "simulate3d"
    photos: list[Path] = []
    """sRGB photographs whose crops texture the planes (plane i uses photo i mod n); empty:
    the bundled office photo."""
    frames: Annotated[int, Field(gt=0)] = 20_000
    """Number of binary frames T."""
    height: Annotated[int, Field(gt=0)] = 254
    """Frame height in pixels."""
    width: Annotated[int, Field(gt=0, multiple_of=8)] = 496
    """Frame width in pixels, a multiple of 8 (frames are bit-packed)."""
    focal_px: Annotated[float, Field(gt=0)] = 420.0
    """Focal length in pixels (fx = fy); the principal point is the frame centre."""
    frame_rate_hz: Annotated[float, Field(gt=0)] = 100_000.0
    """Binary frames per second."""
    flux: Annotated[float, Field(gt=0)] = 0.5
    """Mean photons per pixel per binary frame where a texture is white."""
    path_m: Annotated[float, Field(ge=0, le=1.5)] = 0.36
    """Length of the camera's sideways travel in metres (with a gentle arc and a pan that
    keeps the room in view)."""
    pan_deg: Annotated[float, Field(ge=0, le=20)] = 4.0
    """Total yaw change over the capture in degrees."""
    vibration_mm: Annotated[float, Field(ge=0)] = 2.0
    """Amplitude of the vibration of the camera centre in millimetres."""
    vibration_deg: Annotated[float, Field(ge=0)] = 0.15
    """Amplitude of the rotational vibration in degrees."""
    vibration_hz: Annotated[float, Field(ge=0)] = 30.0
    """Frequency of the vibration in Hz."""
    seed: Annotated[int, Field(ge=0)] = 0
    """Random seed of the photon draws, the texture crops and the vibration phases."""

    def build(self) -> SimulatedRoom:
        """Simulate the capture (about 1 ms per binary frame, threaded)."""
        return SimulatedRoom(self)


def camera_poses(config: Simulate3DConfig) -> NDArray[np.float64]:
    """Return the true camera-to-world poses of ``config``'s path.

    The centre moves ``path_m`` along x (centred on the origin) on a gentle arc (y, z a
    few centimetres), the camera yaws ``pan_deg`` over the capture, and a vibration of
    ``vibration_mm`` / ``vibration_deg`` at ``vibration_hz`` (seeded phases per axis) is
    added to centre and rotation.

    Returns:
        (T, 4, 4) float64 poses, metres, OpenCV camera axes.
    """
    from scipy.spatial.transform import Rotation

    n = config.frames
    s = (np.arange(n) - (n - 1) / 2) / max(n - 1, 1)  # -0.5 .. 0.5
    seconds = np.arange(n) / config.frame_rate_hz
    rng = np.random.default_rng(config.seed + 104729)
    phase = rng.uniform(0, 2 * np.pi, size=6)
    wave = np.sin(2 * np.pi * config.vibration_hz * seconds[:, None] + phase[None])
    centre = np.stack(
        [config.path_m * s, -0.08 * (1 - 4 * s**2) * config.path_m, 0.15 * config.path_m * s], 1
    )
    centre += 1e-3 * config.vibration_mm * wave[:, :3] * np.array([1.0, 1.0, 0.5])
    angles = np.deg2rad(config.vibration_deg) * wave[:, 3:]
    angles[:, 1] += np.deg2rad(config.pan_deg) * s  # yaw about y
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    poses[:, :3, 3] = centre
    poses[:, 3, 3] = 1
    return poses


class SimulatedRoom(PhotonSource):
    """A simulated photon cube of a piecewise-planar room, held bit-packed in memory.

    Attributes:
        cube: (T, H, W/8) uint8 bit-packed binary frames, MSB first.
        ground_truth_poses: (T, 4, 4) float64 true camera-to-world poses (metres, OpenCV axes).
        intrinsics: the true :class:`photonpano.pose.Intrinsics`.
        planes: list of ``(H_texture_to_world (4, 3), texture (h, w) float32)`` of the room.
    """

    def __init__(self, config: Simulate3DConfig) -> None:
        """Simulate every binary frame of ``config``.

        Raises:
            SourceError: if a photo is unreadable.
        """
        from photonpano.photons import draw_binary_frames
        from photonpano.pose import Intrinsics

        self.config = config
        self.n_frames, self.height, self.width = config.frames, config.height, config.width
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = 1.0 / config.frame_rate_hz
        self.intrinsics = Intrinsics(
            config.focal_px, config.focal_px, (config.width - 1) / 2, (config.height - 1) / 2
        )
        self.ground_truth_poses = camera_poses(config)
        photos = list(config.photos) or [bundled_photo()]
        self.planes = self._textures(photos)
        self.name = f"simulate3d({', '.join(p.name for p in photos)}, flux {config.flux})"
        self.cube = np.empty((config.frames, config.height, config.width // 8), np.uint8)

        draw_binary_frames(self.cube, self.render, config.flux, config.seed, task="simulate3d")

    def _textures(self, photos: list[Path]) -> list[tuple[NDArray[np.float64], NDArray[np.float32]]]:
        """Cut one texture per plane from the photos (seeded crops), about one texel per frame pixel."""
        import cv2

        rng = np.random.default_rng(self.config.seed + 15485863)
        scenes = [load_scene(p, 1440) for p in photos]
        planes = []
        for i, (p0, u, v, (su, sv), depth) in enumerate(ROOM_PLANES):
            scene = scenes[i % len(scenes)]
            metres_per_px = depth / self.config.focal_px
            w, h = max(2, round(su / metres_per_px)), max(2, round(sv / metres_per_px))
            hs, ws = scene.shape
            crop_w = max(8, int(min(ws, hs * w / h) * rng.uniform(0.45, 0.8)))
            crop_h = max(8, int(crop_w * h / w))
            x0 = int(rng.integers(0, ws - crop_w + 1))
            y0 = int(rng.integers(0, hs - crop_h + 1))
            texture = cv2.resize(
                scene[y0 : y0 + crop_h, x0 : x0 + crop_w], (w, h), interpolation=cv2.INTER_AREA
            )
            texture = np.clip(0.05 + 0.95 * texture, 0, 1).astype(np.float32)  # no pitch-black walls
            to_world = np.zeros((4, 3))
            to_world[:3, 0] = np.asarray(u, float) * su / w
            to_world[:3, 1] = np.asarray(v, float) * sv / h
            to_world[:3, 2] = p0
            to_world[3, 2] = 1
            planes.append((to_world, np.dstack([texture, np.ones_like(texture)])))
        return planes

    def render(self, t: int) -> NDArray[np.float32]:
        """Render the linear intensity seen by binary frame ``t``.

        Returns:
            (H, W) float32 in [0, 1]; 0 where no plane is seen.
        """
        import cv2

        pose = self.ground_truth_poses[t]
        k = self.intrinsics.matrix()
        world_to_cam = np.linalg.inv(pose)[:3]
        image = np.zeros((self.height, self.width), np.float32)
        for to_world, texture in self.planes:
            h = k @ world_to_cam @ to_world
            th, tw = texture.shape[:2]
            corners = h @ np.array([[0, tw - 1, 0, tw - 1], [0, 0, th - 1, th - 1], [1, 1, 1, 1]], float)
            xy = corners[:2] / corners[2]  # every plane lies in front of every camera of the path
            x0, y0 = np.maximum(np.floor(xy.min(1)).astype(int) - 1, 0)
            x1 = min(int(np.ceil(xy[0].max())) + 2, self.width)
            y1 = min(int(np.ceil(xy[1].max())) + 2, self.height)
            if x1 <= x0 or y1 <= y0:
                continue
            shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], float)
            warped = cv2.warpPerspective(texture, shift @ h, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR)
            roi = image[y0:y1, x0:x1]
            roi *= 1 - warped[..., 1]
            roi += warped[..., 0]
        return image

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges (see :meth:`PhotonSource.sum_ranges`)."""
        from photonpano.photons import sum_packed_ranges

        return sum_packed_ranges(self.cube, edges)

    def describe(self) -> dict:
        """Return the capture summary with the true intrinsics."""
        return {**super().describe(), "intrinsics": self.intrinsics.as_dict()}


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``simulate3d`` source."""
    return [Simulate3DConfig]
