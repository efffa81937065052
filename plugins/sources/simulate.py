"""Source ``simulate``: a SPAD capture simulated from a real photograph.

As in the paper (Sec. 5, "Simulation Details"): the photograph's sRGB tone curve is
undone to get linear intensity, the camera's field of view follows a known path across
it, and every binary frame is drawn from Eq. (2), ``P(1) = 1 - exp(-flux * I)``.
Real-scene nuisances can be added (all off by default): a flickering mains lamp over part
of the scene, a bright disc moving across it, hot pixels and dark counts.

**Colour filters** (``cfa``, off by default): a colour-filtered sensor such as the
SwissSPAD2 colour half array (red, green or blue filters on one pixel in four, the real
layout with ``cfa: colorspad``). The photo's linear R, G, B channels are kept; an
unfiltered pixel sees the Rec. 709 luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` (the
monochrome simulation, so ``scene_flux`` is unchanged) and a pixel behind filter c sees
``cfa_transmission * C`` (C its linear channel: a white scene gives a filtered pixel
``cfa_transmission`` of an unfiltered pixel's photons). As the SwissSPAD sources do,
:meth:`SimulatedCapture.sum_ranges` inpaints the filtered pixels from their unfiltered
neighbours (registration and the main panorama see luminance at every pixel) and
:meth:`SimulatedCapture.raw_sums` keeps them, with the layout in ``corrector.cfa``, for
the colour compositor (:mod:`photonpano.plugins.compositors.colour`); ``scene_flux_rgb``
is the true colour scene.
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.outputs import atomic_path
from photonpano.plugins.sources._capture_config import ColourSourceConfig
from photonpano.stages import PhotonSource, SourceConfig
from pydantic import Field

from ._simulated_scene import (
    LAMP_RAMP_PX,
    bundled_photo,
    camera_path,
    capture_name,
    lamp_edge,
    lamp_factors,
    lamp_mask,
    load_scene,
    paint_disc,
)


class SimulateConfig(ColourSourceConfig):
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
    speed_swing: Annotated[float, Field(ge=0, le=1)] = 0.0
    """Stop-and-go: the pan's speed swings between ``1 - speed_swing`` and ``1 + speed_swing``
    times ``speed_px_per_frame``, slowest at the middle frame (1: the camera halts there)."""
    swing_period_frames: Annotated[int, Field(gt=0)] = 10_000
    """speed_swing: frames per swing of the speed (one halt per period at ``speed_swing`` 1)."""
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
    vibration_model: Literal["translation", "rotation"] = "translation"
    """What vibrates: the frame slides over the scene (``translation``), or a pinhole camera
    of focal length ``focal_px`` turns about its centre (``rotation``: yaw and pitch moving
    the frame centre by ``vibration_px`` on the same circle, as a hand-held camera shakes),
    which vibrates the frame's perspective too: at 5 px and 420 px a corner of a 496x254
    frame moves up to 2.2 px more or less than the centre."""
    pan_model: Literal["translation", "rotation"] = "translation"
    """How the camera follows its path (the pan, the zigzag sweep, the shake): it slides over
    the scene (``translation``), or a pinhole camera of focal length ``focal_px`` turns about
    its centre, as on a tripod (``rotation``: a yaw moving the frame centre by the path's x, a
    pitch by its y; the vibration then turns the camera too). Turned away from the middle of
    the capture, the frames see the flat scene in perspective: a pan of 400 px at 420 px
    turns the camera by 50 degrees, and a frame at either end spans 660 px of the scene,
    against 496 in the middle."""
    focal_px: Annotated[float, Field(gt=0)] = 420.0
    """``vibration_model`` or ``pan_model`` ``rotation``: focal length of the pinhole camera
    in frame pixels."""
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
    flicker_hz: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    """Flicker frequency in Hz of a mains-powered lamp lighting ``flicker_region`` (the
    light's own frequency, twice the mains': 100 for 50 Hz mains, 120 for 60 Hz); 0: no
    flicker. The lamp is a rectified sine: the lit part's intensity is multiplied by
    ``1 - flicker_depth * (1 - abs(sin(pi * flicker_hz * t)))`` (t in seconds), averaged over
    each binary frame's exposure; ``scene_flux`` has the lamp's mean level over the capture."""
    flicker_depth: Annotated[float, Field(ge=0, le=1)] = 0.9
    """Modulation depth of the flicker: the lit part dims to ``1 - flicker_depth`` of its
    level at the lamp's troughs (1: the lamp goes dark twice per mains cycle)."""
    flicker_region: Literal["all", "left", "right", "top", "bottom"] = "all"
    """Part of the scene lit by the flickering lamp, in scene coordinates (it moves with
    the scene, as a lamp lighting part of a room): the whole scene or the half on one side
    of its centre line, with a 20-scene-pixel linear ramp between lit and steady parts."""
    mover_radius_px: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    """Radius in scene pixels of a bright disc moving across the scene independently of
    the camera (anti-aliased over about 1 scene pixel); 0: no moving object. It is not in
    ``scene_flux``; its centres are in ``mover_centres``."""
    mover_speed_px_per_frame: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.08
    """Speed of the moving disc in scene pixels per binary frame (0: a static disc). It
    passes the scene's centre at the capture's middle frame, ``(frames - 1) / 2``."""
    mover_intensity: Annotated[float, Field(gt=0, le=1)] = 1.0
    """Linear intensity of the moving disc (1: as bright as the photo's white); steady, not
    lit by the flickering lamp."""
    mover_direction_deg: Annotated[float, Field(allow_inf_nan=False)] = 0.0
    """Direction of the disc's travel in the scene in degrees: 0 = +x (right), 90 = +y (down)."""
    hot_pixel_fraction: Annotated[float, Field(ge=0, le=0.1)] = 0.0
    """Fraction of the sensor's pixels that are hot (chosen with ``seed``, fixed on the
    sensor): each fires with probability ``hot_pixel_rate`` in every binary frame,
    whatever the scene. Not in ``scene_flux``; the pixels are in ``hot_pixel_mask``."""
    hot_pixel_rate: Annotated[float, Field(gt=0, le=1)] = 0.5
    """Probability that a hot pixel fires in a binary frame."""
    dark_count_rate: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    """Dark counts in counts per pixel per binary frame, on every pixel:
    ``P(1) = 1 - exp(-(flux * I + dark_count_rate))``. Not in ``scene_flux``."""
    cfa: Literal["colorspad"] | Path | None = None
    """Colour filter array of the simulated sensor, as the SwissSPAD sources' ``cfa``: an RGB
    image (white = no filter, pure red/green/blue = that filter) or an ``.npy`` of codes
    (-1 none, 0 R, 1 G, 2 B), cropped to its top-left ``height x width``; ``colorspad``:
    the bundled real SwissSPAD2 colour half-array layout. None: a monochrome sensor. The
    moving disc, hot pixels and dark counts are added alike behind every filter (hot
    pixels are not inpainted)."""
    cfa_transmission: Annotated[float, Field(gt=0, le=1)] = 1 / 3
    """Filter transmission: a pixel behind filter c sees ``cfa_transmission`` times the
    photo's linear channel c (an unfiltered pixel sees the luminance). 1/3: a filter
    passing one of three equal bands of white light."""
    colour_panorama: bool = False
    """Also write ``panorama_rgb.npy`` / ``.tif`` / ``.png`` (needs ``cfa``), as the
    SwissSPAD sources do."""

    def build(self) -> SimulatedCapture:
        """Simulate the capture (takes about 0.5 ms per binary frame)."""
        return SimulatedCapture(self)


class SimulatedCapture(PhotonSource):
    """A simulated photon cube held bit-packed in memory (or in ``cube_path``).

    Nuisances (all off by default): a flickering lamp over part of the scene, a bright
    disc moving across it, hot pixels and dark counts (see :class:`SimulateConfig`).

    Attributes:
        cube: (T, H, W/8) uint8 bit-packed binary frames, MSB first.
        ground_truth: (T, 3, 3) float64 true frame-to-scene homographies (the camera
            path; the moving disc does not change it).
        scene_flux: (Hs, Ws) float32 true flux in photons/s of the static scene: without
            the moving disc, hot pixels and dark counts, the flickering lamp's part at the
            lamp's mean level over the capture (so a panorama compares with it).
        lamp: (T,) float64 the flickering lamp's relative level per frame (ones when off).
        mover_centres: (T, 2) float64 scene ``(x, y)`` of the moving disc's centre per
            frame; None without one.
        hot_pixel_mask: (H, W) bool, the hot pixels; None without them.
        corrector: with ``cfa``, the :class:`~photonpano.plugins.sources._swissspad_sensor.SensorCorrector`
            that inpaints the filtered pixels in :meth:`sum_ranges`; its ``cfa`` holds the
            (H, W) int8 codes (-1 none, 0/1/2 R/G/B), as the SwissSPAD sources'; None without.
        scene_flux_rgb: with ``cfa``, (Hs, Ws, 3) float32 true flux in photons/s behind
            the R, G and B filters (``flux * cfa_transmission * C / exposure_s``, the
            flickering lamp at its mean level as in ``scene_flux``), on ``scene_flux``'s
            grid; None without.
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
        rgb = None
        if config.cfa is not None:
            rgb = load_scene(photo, config.scene_width, colour=True)
            scene = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)  # the luminance of load_scene
        else:
            scene = load_scene(photo, config.scene_width)
        if config.mean_intensity is not None:
            gain = np.float32(config.mean_intensity / max(float(scene.mean()), 1e-12))
            scene = np.minimum(scene * gain, 1)
            rgb = None if rgb is None else np.minimum(rgb * gain, 1)
        self.n_frames, self.height, self.width = config.frames, config.height, config.width
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = 1.0 / config.frame_rate_hz
        pitch = config.pixel_pitch
        to_scene = camera_path(config, scene.shape[:2]) @ scale_matrix(pitch)  # frame pixels -> scene pixels
        self.ground_truth = geometry.normalize(scale_matrix(1.0 / pitch) @ to_scene)
        self.lamp = lamp_factors(config)
        level: np.float32 | NDArray[np.float32] = np.float32(1)  # the flickering lamp's mean level over the capture
        if config.flicker_hz > 0:
            level = 1 + lamp_mask(scene.shape, config.flicker_region) * np.float32(self.lamp.mean() - 1)
        self.scene_flux = (config.flux * (scene * level) / self.exposure_s).astype(np.float32)
        self.scene_pitch = float(pitch)
        self.corrector, self.scene_flux_rgb = None, None
        if rgb is not None:
            from ._swissspad_sensor import SensorCorrector, SwissSpadCorrections

            self.corrector = SensorCorrector(SwissSpadCorrections.model_construct(cfa=config.cfa),
                                             (config.height, config.width), None, "simulate")
            transmission = np.float32(config.cfa_transmission)
            self.scene_flux_rgb = (np.float32(config.flux / self.exposure_s) * transmission
                                   * rgb * np.asarray(level)[..., None]).astype(np.float32)
            # each pixel's intensity: channel 0 the luminance, 1-3 R, G, B through the filter
            scene = np.concatenate([scene[..., None], transmission * rgb], axis=-1)
        self.mover_centres = None
        if config.mover_radius_px > 0:
            angle = np.deg2rad(config.mover_direction_deg)
            velocity = config.mover_speed_px_per_frame * np.array([np.cos(angle), np.sin(angle)])
            steps = np.arange(config.frames, dtype=np.float64) - (config.frames - 1) / 2
            centre = np.array([(scene.shape[1] - 1) / 2, (scene.shape[0] - 1) / 2])  # (Hs, Ws) luminance
            self.mover_centres = centre + steps[:, None] * velocity
        self.hot_pixel_mask = None
        n_hot = round(config.hot_pixel_fraction * config.height * config.width)
        if n_hot > 0:
            # its own stream: the photon draws (seed, t) stay those of the capture without hot pixels
            rng = np.random.default_rng([config.seed, 0x40770])
            self.hot_pixel_mask = np.zeros((config.height, config.width), bool)
            self.hot_pixel_mask.flat[rng.choice(config.height * config.width, n_hot, replace=False)] = True
        self.name = capture_name(config, photo)

        shape = (config.frames, config.height, config.width // 8)
        if config.cube_path is not None and config.cube_path.exists():
            raise SourceError(f"source (simulate): cube_path {config.cube_path} exists; refusing to overwrite it")
        # the cube file is written under a temporary name and renamed when complete
        with atomic_path(config.cube_path) if config.cube_path is not None else nullcontext() as tmp:
            self.cube: NDArray[np.uint8] = (np.empty(shape, dtype=np.uint8) if tmp is None else
                                            np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=shape))
            self._render(scene, to_scene)

    def _render(self, scene: NDArray[np.float32], to_scene: NDArray[np.float64]) -> None:
        """Draw every binary frame: ``to_scene`` (T, 3, 3) maps frame pixels to scene pixels."""
        from photonpano.photons import draw_binary_frames

        config = self.config
        draw_binary_frames(self.cube, self._intensity(scene, to_scene), config.flux, config.seed)
        if isinstance(self.cube, np.memmap):
            self.cube.flush()

    def _intensity(self, scene: NDArray[np.float32], to_scene: NDArray[np.float64]):
        """Return ``intensity(t)``: frame t's intensity, the scene warped, with the configured nuisances.

        The values are ``I'`` with ``flux * I' = flux * I + dark_count_rate`` (above 1
        where dark counts add, ``draw_binary_frames`` takes ``1 - exp(-flux * I')`` as it
        is) and, at hot pixels, ``-ln(1 - hot_pixel_rate) / flux``.
        """
        import cv2

        config = self.config
        size = (config.width, config.height)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        lamp = self.lamp.astype(np.float32)
        split = config.flicker_hz > 0 and config.flicker_region != "all"
        if split:
            # the lamp's share at each frame pixel, from the frame pixel's scene coordinate
            # (the ramp of lamp_mask evaluated there; 10x cheaper than warping the mask too):
            # share = clip(a x + b y + c) for an affine to_scene, else through the division
            axis, sign, centre = lamp_edge(scene.shape[:2], config.flicker_region)
            row = to_scene[:, axis] * (sign / LAMP_RAMP_PX)
            row[:, 2] += 0.5 - sign * centre / LAMP_RAMP_PX
            affine = bool(np.all(to_scene[:, 2, :2] == 0) and np.all(to_scene[:, 2, 2] == 1))
            xs = np.arange(config.width, dtype=np.float32)
            ys = np.arange(config.height, dtype=np.float32)
            corners = np.array([[0, 0, 1], [config.width - 1, 0, 1], [0, config.height - 1, 1],
                                [config.width - 1, config.height - 1, 1]], dtype=np.float64)

            def lamp_share(t: int) -> NDArray[np.float32] | float:
                if affine:
                    at_corners = row[t] @ corners.T  # the share is linear: its extremes are at corners
                    if at_corners.max() <= 0:
                        return 0.0
                    if at_corners.min() >= 1:
                        return 1.0
                    a, b, c = row[t].astype(np.float32)
                    if b == 0:  # no rotation: one row (or column) broadcast over the frame
                        share = (a * xs + c)[None, :]
                    elif a == 0:
                        share = (b * ys + c)[:, None]
                    else:
                        share = a * xs[None, :] + (b * ys + c)[:, None]
                else:
                    h = to_scene[t]
                    num = h[axis, 0] * xs[None, :] + (h[axis, 1] * ys + h[axis, 2])[:, None]
                    den = h[2, 0] * xs[None, :] + (h[2, 1] * ys + h[2, 2])[:, None]
                    share = (0.5 + sign * (num / den - centre) / LAMP_RAMP_PX).astype(np.float32)
                return np.clip(share, 0, 1, out=share)
        offset = np.float32(config.dark_count_rate / config.flux)
        hot = None
        if self.hot_pixel_mask is not None:
            hot = np.flatnonzero(self.hot_pixel_mask)
            with np.errstate(divide="ignore"):  # rate 1: infinite intensity, P(1) = 1
                hot_level = np.float32(-np.log1p(-config.hot_pixel_rate) / config.flux)
        disc = None
        if self.mover_centres is not None:
            # the disc's centre in frame pixels, and the frame's scene pixels per frame pixel
            inverse = np.linalg.inv(to_scene)
            centres = np.einsum("tij,tj->ti", inverse, np.column_stack([self.mover_centres, np.ones(len(inverse))]))
            centres = centres[:, :2] / centres[:, 2:]
            scales = np.sqrt(np.abs(np.linalg.det(to_scene[:, :2, :2] / to_scene[:, 2:, 2:])))
            disc = (centres, scales, config.mover_radius_px, np.float32(config.mover_intensity))

        pick = None
        if scene.ndim == 3:  # colour filters: each pixel's channel (0 luminance, 1-3 R, G, B)
            # a colour scene is simulated through the CFA of its corrector (both made in __init__)
            assert self.corrector is not None and self.corrector.cfa is not None
            pick = (self.corrector.cfa.astype(np.intp) + 1)[..., None]

        def intensity(t: int) -> NDArray[np.float32]:
            image = np.asarray(cv2.warpPerspective(scene, to_scene[t], size, flags=flags), np.float32)  # no copy
            if pick is not None:
                image = np.take_along_axis(image, pick, axis=2)[..., 0]
            if split:
                share = lamp_share(t)
                if isinstance(share, np.ndarray):  # (H, W), (1, W) or (H, 1)
                    share *= lamp[t] - 1
                    share += 1
                    image *= share
                elif share:
                    image *= lamp[t]
            elif config.flicker_hz > 0:
                image *= lamp[t]
            if disc is not None:
                paint_disc(image, disc[0][t], disc[1][t], disc[2], disc[3])
            if offset:
                image += offset
            if hot is not None:
                image.reshape(-1)[hot] = hot_level
            return image

        return intensity

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges (see :meth:`PhotonSource.sum_ranges`).

        With ``cfa`` the filtered pixels are inpainted from their unfiltered neighbours
        (:meth:`~photonpano.plugins.sources._swissspad_sensor.SensorCorrector.apply`).
        """
        counts = self.raw_sums(edges)
        return counts if self.corrector is None else self.corrector.apply(counts, np.asarray(edges, np.int64))

    def raw_sums(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """(B, H, W) uint16 detections over frame ranges, filtered pixels as they are."""
        from photonpano.photons import sum_packed_ranges

        return sum_packed_ranges(self.cube, edges)


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``simulate`` source."""
    return [SimulateConfig]
