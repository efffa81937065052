"""Source ``simulate``: a SPAD capture simulated from a real photograph.

As in the paper (Sec. 5, "Simulation Details"): the photograph's sRGB tone curve is
undone to get linear intensity, the camera's field of view follows a known path across
it, and every binary frame is drawn from Eq. (2), ``P(1) = 1 - exp(-flux * I)``.
"""

from __future__ import annotations

from contextlib import nullcontext
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.outputs import atomic_path
from photonpano.stages import PhotonSource, SourceConfig
from pydantic import Field

BUNDLED_PHOTO = "office_equirect.jpg"


def bundled_photo() -> Path:
    """Return the path of the bundled real photograph (see ``plugins/data/SOURCES.md``)."""
    return Path(str(resources.files("photonpano.plugins") / "data" / BUNDLED_PHOTO))


class SimulateConfig(SourceConfig):
    """Simulate binary frames of a camera moving across a real photograph."""

    plugin: Literal["simulate"] = "simulate"
    photo: Path | None = None
    """sRGB photograph (JPEG/PNG) to look at; default: the bundled office photo."""
    scene_width: Annotated[int, Field(gt=0)] = 1440
    """The photo is resized to this width in pixels before simulation. Camera pixels
    have unit size in the resized photo at zoom 1, so errors are in these "scene pixels"."""
    frames: Annotated[int, Field(gt=0)] = 20_000
    """Number of binary frames T."""
    height: Annotated[int, Field(gt=0)] = 254
    """Frame height in pixels (254 for a SwissSPAD2 half array after the colour fix)."""
    width: Annotated[int, Field(gt=0, multiple_of=8)] = 496
    """Frame width in pixels, a multiple of 8 (frames are bit-packed)."""
    frame_rate_hz: Annotated[float, Field(gt=0)] = 100_000.0
    """Binary frames per second; the exposure of one frame is 1 / frame_rate_hz."""
    flux: Annotated[float, Field(gt=0)] = 0.5
    """Light level: mean photons per pixel per binary frame where the photo is white."""
    path: Literal["pan", "zigzag", "shake"] = "pan"
    """Camera path: horizontal pan; pan with a vertical triangle sweep; or a pan plus a
    smooth random shake (sum of seeded random sinusoids)."""
    speed_px_per_frame: float = 0.02
    """Horizontal pan speed in scene pixels per binary frame."""
    sweep_px: Annotated[float, Field(ge=0)] = 40.0
    """zigzag: peak vertical excursion in scene pixels."""
    sweep_period_frames: Annotated[int, Field(gt=0)] = 20_000
    """zigzag: frames per full up-and-down sweep."""
    shake_px: Annotated[float, Field(ge=0)] = 8.0
    """shake: RMS displacement of the random shake in scene pixels (0.5-10 Hz content)."""
    vibration_px: Annotated[float, Field(ge=0)] = 5.0
    """Amplitude of a circular high-frequency vibration in scene pixels."""
    vibration_hz: Annotated[float, Field(ge=0)] = 30.0
    """Frequency of the vibration in Hz."""
    rotation_deg: Annotated[float, Field(ge=0)] = 0.0
    """Amplitude of an in-plane rotation oscillation in degrees."""
    rotation_hz: Annotated[float, Field(ge=0)] = 2.0
    """Frequency of the rotation oscillation in Hz."""
    zoom: Annotated[float, Field(ge=0, lt=0.5)] = 0.0
    """Relative amplitude of a zoom oscillation (0.05 = +-5 % scale)."""
    zoom_hz: Annotated[float, Field(ge=0)] = 2.0
    """Frequency of the zoom oscillation in Hz."""
    seed: Annotated[int, Field(ge=0)] = 0
    """Random seed of the photon draws and of the shake path."""
    cube_path: Path | None = None
    """Also write the binary frames to this bit-packed ``.npy`` cube (must not exist)."""
    pixel_pitch: Annotated[int, Field(ge=1, le=8)] = 1
    """Distance between frame pixels in scene pixels. Frame pixels are point samples of
    the scene (a sensor with a small fill factor, as SwissSPAD2's 10.5 %): at 2 a frame
    of ``height x width`` pixels covers ``2 height x 2 width`` scene pixels and
    undersamples the scene 2x (the test of super-resolution). The camera path and its
    speeds stay in scene pixels; ``ground_truth`` is in frame pixels (scene coordinates
    divided by the pitch) and ``scene_flux`` at scene resolution (``scene_pitch``)."""
    mean_intensity: Annotated[float, Field(gt=0, le=1)] | None = None
    """Scale the photo's linear intensity so that its mean is this (e.g. 0.016 for a
    dark scene; values are clipped at 1); None: the photo as it is."""

    def build(self) -> SimulatedCapture:
        """Simulate the capture (takes about 0.5 ms per binary frame)."""
        return SimulatedCapture(self)


def camera_path(config: SimulateConfig, scene_shape: tuple[int, int]) -> NDArray[np.float64]:
    """Return the true frame-to-scene homographies of the simulated camera.

    ``H[t] = T(centre + offset(t)) R(theta(t)) S(zoom(t)) T(-frame_centre)``: a frame
    pixel ``(x, y)`` of binary frame t sees scene pixel ``H[t] @ (x, y, 1)``, frame
    pixels measured in scene pixels (a frame spans ``pixel_pitch`` times its size in
    pixels).

    Args:
        config: the simulation settings.
        scene_shape: ``(height, width)`` of the scene in pixels.

    Returns:
        (T, 3, 3) float64 homographies.

    Raises:
        SourceError: if the camera's field of view leaves the scene.
    """
    n, fps = config.frames, config.frame_rate_hz
    t = np.arange(n, dtype=np.float64)
    s = t / fps
    x = config.speed_px_per_frame * (t - (n - 1) / 2)
    y = np.zeros(n)
    if config.path == "zigzag":
        phase = (t / config.sweep_period_frames) % 1.0
        y = config.sweep_px * (4 * np.abs(phase - 0.5) - 1)
    elif config.path == "shake":
        rng = np.random.default_rng(config.seed + 7919)
        freqs = rng.uniform(0.5, 10.0, size=(2, 6))
        phases = rng.uniform(0, 2 * np.pi, size=(2, 6))
        amps = 1.0 / freqs
        shake = np.einsum("ak,akn->an", amps, np.sin(2 * np.pi * freqs[..., None] * s + phases[..., None]))
        shake *= config.shake_px / max(float(np.sqrt(np.mean(shake ** 2))), 1e-12) / np.sqrt(2)
        x, y = x + shake[0], y + shake[1]
    w = 2 * np.pi * config.vibration_hz * s
    x = x + config.vibration_px * np.sin(w)
    y = y + config.vibration_px * np.cos(w)
    theta = np.deg2rad(config.rotation_deg) * np.sin(2 * np.pi * config.rotation_hz * s)
    zoom = 1.0 + config.zoom * np.sin(2 * np.pi * config.zoom_hz * s)

    hs, ws = scene_shape
    width, height = config.width * config.pixel_pitch, config.height * config.pixel_pitch
    cx, cy = (width - 1) / 2, (height - 1) / 2
    c, si = np.cos(theta) * zoom, np.sin(theta) * zoom
    h = np.zeros((n, 3, 3))
    h[:, 0, 0], h[:, 0, 1] = c, -si
    h[:, 1, 0], h[:, 1, 1] = si, c
    h[:, 0, 2] = (ws - 1) / 2 + x - (c * cx - si * cy)
    h[:, 1, 2] = (hs - 1) / 2 + y - (si * cx + c * cy)
    h[:, 2, 2] = 1

    from photonpano.geometry import footprint_bounds

    x0, y0, x1, y1 = footprint_bounds(h, width, height)
    if x0 < 0 or y0 < 0 or x1 > ws - 1 or y1 > hs - 1:
        raise SourceError(
            f"source (simulate): the camera path leaves the {ws}x{hs} scene "
            f"(field of view spans x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f}); "
            "reduce frames, speed_px_per_frame or the motion amplitudes, or raise scene_width"
        )
    return h


def load_scene(photo: Path, scene_width: int) -> NDArray[np.float32]:
    """Load a photograph as linear luminance resized to ``scene_width`` pixels.

    Args:
        photo: path of an sRGB image readable by OpenCV.
        scene_width: output width in pixels (the height keeps the aspect ratio).

    Returns:
        (Hs, Ws) float32 linear luminance in [0, 1] (Rec. 709 weights).

    Raises:
        SourceError: if the file is missing or cannot be decoded.
    """
    import cv2
    from photonpano.photons import srgb_to_linear

    if not photo.is_file():
        raise SourceError(f"source (simulate): photo {photo} does not exist")
    bgr = cv2.imread(str(photo), cv2.IMREAD_COLOR)
    if bgr is None:
        raise SourceError(f"source (simulate): {photo} is not an image OpenCV can decode")
    # the 256 sRGB codes through a table, then the weighted channel sum: 20x faster on a
    # 13-megapixel photo than the curve evaluated per pixel (2.4 s -> 0.1 s), within 1e-7
    linear = cv2.LUT(bgr, srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255)))
    lum = cv2.transform(linear, np.array([[0.0722, 0.7152, 0.2126]], dtype=np.float32))  # BGR order
    height = max(1, round(bgr.shape[0] * scene_width / bgr.shape[1]))
    return cv2.resize(lum, (scene_width, height), interpolation=cv2.INTER_AREA)


class SimulatedCapture(PhotonSource):
    """A simulated photon cube held bit-packed in memory (or in ``cube_path``).

    Attributes:
        cube: (T, H, W/8) uint8 bit-packed binary frames, MSB first.
        ground_truth: (T, 3, 3) float64 true frame-to-scene homographies.
        scene_flux: (Hs, Ws) float32 true scene flux in photons/s.
    """

    def __init__(self, config: SimulateConfig) -> None:
        """Simulate every binary frame of ``config``.

        Raises:
            SourceError: if the photo is unreadable, the path leaves the scene or
                ``cube_path`` already exists.
        """
        from photonpano import geometry
        from photonpano.geometry import scale_matrix

        self.config = config
        photo = config.photo or bundled_photo()
        scene = load_scene(photo, config.scene_width)
        if config.mean_intensity is not None:
            scene = np.minimum(scene * np.float32(config.mean_intensity / max(float(scene.mean()), 1e-12)), 1)
        self.n_frames, self.height, self.width = config.frames, config.height, config.width
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = 1.0 / config.frame_rate_hz
        pitch = config.pixel_pitch
        to_scene = camera_path(config, scene.shape) @ scale_matrix(pitch)  # frame pixels -> scene pixels
        self.ground_truth = geometry.normalize(scale_matrix(1.0 / pitch) @ to_scene)
        self.scene_flux = (config.flux * scene / self.exposure_s).astype(np.float32)
        self.scene_pitch = float(pitch)
        self.name = f"simulate({photo.name}, {config.path}, flux {config.flux})"

        shape = (config.frames, config.height, config.width // 8)
        if config.cube_path is not None and config.cube_path.exists():
            raise SourceError(f"source (simulate): cube_path {config.cube_path} exists; refusing to overwrite it")
        # the cube file is written under a temporary name and renamed when complete
        with atomic_path(config.cube_path) if config.cube_path is not None else nullcontext() as tmp:
            if tmp is not None:
                self.cube = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=shape)
            else:
                self.cube = np.empty(shape, dtype=np.uint8)
            self._render(scene, to_scene)

    def _render(self, scene: NDArray[np.float32], to_scene: NDArray[np.float64]) -> None:
        """Draw every binary frame: ``to_scene`` (T, 3, 3) maps frame pixels to scene pixels."""
        import cv2
        from photonpano.photons import draw_binary_frames

        config = self.config
        size = (config.width, config.height)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        draw_binary_frames(self.cube, lambda t: cv2.warpPerspective(scene, to_scene[t], size, flags=flags),
                           config.flux, config.seed)
        if isinstance(self.cube, np.memmap):
            self.cube.flush()

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges (see :meth:`PhotonSource.sum_ranges`)."""
        from photonpano.photons import sum_packed_ranges

        return sum_packed_ranges(self.cube, edges)


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``simulate`` source."""
    return [SimulateConfig]
