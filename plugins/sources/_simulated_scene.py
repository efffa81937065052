"""The world of the ``simulate`` source: the photograph, the camera's path, the flickering lamp, the moving disc.

Pure functions of a :class:`~photonpano.plugins.sources.simulate.SimulateConfig` (or its
fields); the photon simulation itself is :class:`~photonpano.plugins.sources.simulate.SimulatedCapture`.
Not a plugin (it registers nothing).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from photonpano.errors import SourceError

if TYPE_CHECKING:
    from .simulate import SimulateConfig

__all__ = ["BUNDLED_PHOTO", "LAMP_RAMP_PX", "bundled_photo", "camera_path", "capture_name", "load_scene", "lamp_mask",
           "lamp_edge", "lamp_factors", "paint_disc"]


BUNDLED_PHOTO = "office_equirect.jpg"
LAMP_RAMP_PX = 20.0
"""Width in scene pixels of the ramp between the flickering lamp's lit and steady parts."""


def bundled_photo() -> Path:
    """Return the path of the bundled real photograph (see ``plugins/data/SOURCES.md``)."""
    return Path(str(resources.files("photonpano.plugins") / "data" / BUNDLED_PHOTO))


def camera_path(config: SimulateConfig, scene_shape: tuple[int, int]) -> NDArray[np.float64]:
    """Return the true frame-to-scene homographies of the simulated camera.

    ``H[t] = T(centre + offset(t)) R(theta(t)) S(zoom(t)) T(-frame_centre)``: a frame
    pixel ``(x, y)`` of binary frame t sees scene pixel ``H[t] @ (x, y, 1)``, frame
    pixels measured in scene pixels (a frame spans ``pixel_pitch`` times its size in
    pixels). With ``vibration_model: rotation`` the vibration is not in the offset but a
    turn of a pinhole camera (focal length ``f = focal_px * pixel_pitch``) about its
    centre, applied to the frame first: ``H[t] @ T(frame_centre) K R_t K^-1
    T(-frame_centre)``, ``K = diag(f, f, 1)``, ``R_t`` a yaw of ``atan(a sin(w t) / f)``
    then a pitch of ``atan(a cos(w t) / f)`` (a = ``vibration_px``), which moves the frame
    centre by about ``a`` as the translation would (Hartley and Zisserman, *Multiple View
    Geometry*, 2nd ed., Sec. 8.4.2: a camera rotating about its centre, ``H = K R K^-1``).
    With ``pan_model: rotation`` the whole path turns the camera so: the yaw is
    ``atan((x(t) + a sin(w t)) / f)`` and the pitch ``atan((y(t) + a cos(w t)) / f)``, the
    offset is zero (a camera on a tripod in front of the scene's centre).

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
    if config.speed_swing:  # speed v (1 - swing cos(2 pi (t - middle) / P)): at its slowest in the middle
        period = config.swing_period_frames
        x -= (config.speed_px_per_frame * config.speed_swing * period / (2 * np.pi)
              * np.sin(2 * np.pi * (t - (n - 1) / 2) / period))
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
    turning_path = config.pan_model == "rotation"
    rotating = (config.vibration_model == "rotation" and config.vibration_px > 0) or turning_path
    # what the turning camera's yaw and pitch move the frame centre by (turn_x, turn_y); the rest slides (x, y)
    turn_x, turn_y = (x, y) if turning_path else (np.zeros(n), np.zeros(n))
    if turning_path:
        x, y = np.zeros(n), np.zeros(n)
    if rotating:
        turn_x, turn_y = turn_x + config.vibration_px * np.sin(w), turn_y + config.vibration_px * np.cos(w)
    else:
        x, y = x + config.vibration_px * np.sin(w), y + config.vibration_px * np.cos(w)
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
    if rotating:
        h = h @ _turning_camera(turn_x, turn_y, config.focal_px * config.pixel_pitch, cx, cy)

    from photonpano.geometry import footprint_bounds

    x0, y0, x1, y1 = footprint_bounds(h, width, height)
    if x0 < 0 or y0 < 0 or x1 > ws - 1 or y1 > hs - 1:
        raise SourceError(
            f"source (simulate): the camera path leaves the {ws}x{hs} scene "
            f"(field of view spans x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f}); "
            "reduce frames, speed_px_per_frame or the motion amplitudes, or raise scene_width"
        )
    return h


def _turning_camera(shift_x: NDArray[np.float64], shift_y: NDArray[np.float64], focal: float,
                    cx: float, cy: float) -> NDArray[np.float64]:
    """Homographies of a pinhole camera turned to move its frame centre by about ``(shift_x, shift_y)``.

    Args:
        shift_x: (T,) float64 shift of the frame centre along x (a yaw), in pixels.
        shift_y: (T,) float64 shift along y (a pitch), in pixels.
        focal: focal length in pixels.
        cx: x of the frame centre (the principal point) in pixels.
        cy: y of the frame centre in pixels.

    Returns:
        (T, 3, 3) float64 ``T(c) K R_t K^-1 T(-c)``, frame pixels of the turned camera to
        those of the unturned one, ``R_t`` a yaw of ``atan(shift_x / f)`` then a pitch of
        ``atan(shift_y / f)``.
    """
    yaw, pitch = np.arctan(shift_x / focal), np.arctan(shift_y / focal)
    cos_a, sin_a, cos_b, sin_b = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    n = len(yaw)
    rotation = np.zeros((n, 3, 3))
    # R = R_yaw @ R_pitch, R_yaw = [[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]],
    # R_pitch = [[1, 0, 0], [0, cb, sb], [0, -sb, cb]]
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 0, 2] = cos_a, -sin_a * sin_b, sin_a * cos_b
    rotation[:, 1, 1], rotation[:, 1, 2] = cos_b, sin_b
    rotation[:, 2, 0], rotation[:, 2, 1], rotation[:, 2, 2] = -sin_a, -cos_a * sin_b, cos_a * cos_b
    from photonpano.geometry import translation

    k = np.diag([focal, focal, 1.0])
    out = translation(cx, cy) @ k @ rotation @ np.linalg.inv(k) @ translation(-cx, -cy)
    return out / out[:, 2:3, 2:3]


def capture_name(config: SimulateConfig, photo: Path) -> str:
    """The capture's name in logs and run.json: the photo, the path, the flux and every nuisance simulated.

    Example: ``simulate(city.jpg, pan, flux 0.5, flicker 120 Hz left)``.
    """
    extras = []
    if config.flicker_hz > 0:
        extras.append(f"flicker {config.flicker_hz:g} Hz {config.flicker_region}")
    if config.mover_radius_px > 0:
        extras.append(f"mover r{config.mover_radius_px:g}")
    if round(config.hot_pixel_fraction * config.height * config.width) > 0:
        extras.append(f"hot pixels {config.hot_pixel_fraction:.3g}")
    if config.dark_count_rate > 0:
        extras.append(f"dark counts {config.dark_count_rate:g}")
    if config.cfa is not None:
        extras.append(f"cfa {Path(config.cfa).name}")
    return f"simulate({', '.join([photo.name, config.path, f'flux {config.flux}', *extras])})"


def load_scene(photo: Path, scene_width: int, colour: bool = False) -> NDArray[np.float32]:
    """Load a photograph as linear luminance (or colour) resized to ``scene_width`` pixels.

    Args:
        photo: path of an sRGB image readable by OpenCV.
        scene_width: output width in pixels (the height keeps the aspect ratio).
        colour: return the linear R, G, B channels instead of the luminance.

    Returns:
        (Hs, Ws) float32 linear luminance in [0, 1] (Rec. 709 weights), or with
        ``colour`` (Hs, Ws, 3) float32 linear R, G, B in [0, 1].

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
    height = max(1, round(bgr.shape[0] * scene_width / bgr.shape[1]))
    if colour:
        return np.ascontiguousarray(cv2.resize(linear, (scene_width, height), interpolation=cv2.INTER_AREA)[..., ::-1])
    lum = cv2.transform(linear, np.array([[0.0722, 0.7152, 0.2126]], dtype=np.float32))  # BGR order
    return np.asarray(cv2.resize(lum, (scene_width, height), interpolation=cv2.INTER_AREA), np.float32)  # no copy


def lamp_mask(shape: tuple[int, int], region: str, ramp_px: float = LAMP_RAMP_PX) -> NDArray[np.float32]:
    """Return the share of each scene pixel lit by the flickering lamp.

    Args:
        shape: ``(height, width)`` of the scene in pixels.
        region: ``all``, or the half of the scene (``left``, ``right``, ``top``,
            ``bottom``) on one side of its centre line.
        ramp_px: width in scene pixels of the linear ramp from unlit (0) to lit (1),
            centred on the centre line.

    Returns:
        (Hs, Ws) float32 in [0, 1].
    """
    if region == "all":
        return np.ones(shape, np.float32)
    axis, sign, centre = lamp_edge(shape, region)
    ramp = np.clip(0.5 + sign * (np.arange(shape[1 - axis]) - centre) / ramp_px, 0, 1).astype(np.float32)
    return np.broadcast_to(ramp[None, :] if axis == 0 else ramp[:, None], shape).copy()


def lamp_edge(shape: tuple[int, int], region: str) -> tuple[int, int, float]:
    """Return ``(axis, sign, centre)`` of the lamp's edge in the scene.

    The lamp's share rises along scene coordinate ``axis`` (0: x, 1: y) in direction
    ``sign``, through 0.5 at ``centre``, the scene's centre line.
    """
    hs, ws = shape
    return {"left": (0, -1, (ws - 1) / 2), "right": (0, 1, (ws - 1) / 2),
            "top": (1, -1, (hs - 1) / 2), "bottom": (1, 1, (hs - 1) / 2)}[region]


def lamp_factors(config: SimulateConfig) -> NDArray[np.float64]:
    """Return the flickering lamp's relative level in each binary frame.

    ``1 - depth * (1 - |sin(pi f t)|)`` averaged exactly over frame t's exposure
    ``[t, t + 1) / frame_rate_hz`` (so a flicker near the frame rate does not alias).

    Returns:
        (T,) float64 in [1 - depth, 1]; all ones when ``flicker_hz`` is 0.
    """
    if config.flicker_hz <= 0:
        return np.ones(config.frames)
    # F(u) = integral_0^u |sin v| dv = 2 k + 1 - cos(u - k pi), k = floor(u / pi): continuous
    # in u even where rounding puts k one off at a multiple of pi
    u = np.pi * config.flicker_hz * np.arange(config.frames + 1, dtype=np.float64) / config.frame_rate_hz
    k = np.floor(u / np.pi)
    integral = 2 * k + 1 - np.cos(u - k * np.pi)
    mean_abs_sin = np.diff(integral) / (u[1] - u[0])
    return 1 - config.flicker_depth * (1 - mean_abs_sin)


def paint_disc(image: NDArray[np.float32], centre: NDArray[np.float64], scale: float, radius: float,
                level: np.float32) -> None:
    """Paint an anti-aliased disc into ``image`` in place, only inside its bounding box.

    Args:
        image: (H, W) float32 frame intensity.
        centre: ``(x, y)`` of the disc's centre in frame pixels.
        scale: scene pixels per frame pixel.
        radius: the disc's radius in scene pixels; its edge ramps over 1 scene pixel.
        level: the disc's intensity.
    """
    h, w = image.shape
    reach = (radius + 0.5) / scale
    x0, x1 = max(0, int(np.floor(centre[0] - reach))), min(w, int(np.ceil(centre[0] + reach)) + 1)
    y0, y1 = max(0, int(np.floor(centre[1] - reach))), min(h, int(np.ceil(centre[1] + reach)) + 1)
    if x0 >= x1 or y0 >= y1:
        return
    dx = (np.arange(x0, x1, dtype=np.float32) - np.float32(centre[0]))[None, :]
    dy = (np.arange(y0, y1, dtype=np.float32) - np.float32(centre[1]))[:, None]
    alpha = np.clip(np.float32(radius + 0.5) - np.sqrt(dx * dx + dy * dy) * np.float32(scale), 0, 1)
    box = image[y0:y1, x0:x1]
    box += alpha * (level - box)
