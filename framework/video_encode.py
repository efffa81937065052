"""Encoding a run's video: one white point as ``panorama.png``, 8-bit sRGB, H.264 through PyAV.

Used by :mod:`photonpano.video` (``photonpano video``) and by runs with
``outputs: {video: true}``. PyAV is the ``video`` extra; it is imported when a video is
written, and its absence is a one-line :class:`~photonpano.errors.MissingDependency`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import MissingDependency, PhotonpanoError

__all__ = ["MAX_DEFAULT_WIDTH", "VideoInfo", "require_av", "white_point", "to_codes", "encode"]

MAX_DEFAULT_WIDTH = 3840
"""Without ``width``, a wider canvas is scaled down to this many pixels."""


@dataclass
class VideoInfo:
    """What :func:`render_video` or :func:`encode` wrote.

    Attributes:
        frames: video frames written.
        width: frame width in pixels (even).
        height: frame height in pixels (even).
        codec: the encoder (``libx264``, or ``mpeg4`` where PyAV lacks it).
        notes: one line per adjustment (codec fallback, scaled-down canvas, ...).
    """

    frames: int = 0
    width: int = 0
    height: int = 0
    codec: str = ""
    notes: list[str] = field(default_factory=list)


def require_av() -> Any:
    """Import and return PyAV (``av``).

    Raises:
        MissingDependency: PyAV is not installed (one line naming the ``video`` extra).
    """
    try:
        import av
    except ImportError:
        raise MissingDependency("photonpano video needs PyAV: pip install 'photonpano[video]'") from None
    return av


def white_point(flux: NDArray, percentile: float = 99.5) -> float:
    """The flux mapped to white: the ``percentile``-th percentile of the finite values (nearest rank).

    The white point of :func:`~photonpano.photons.tone_map` (``panorama.png``); 1.0 for
    an image without a positive finite value. ``flux`` is any float array (photons/s).
    """
    values = np.asarray(flux, np.float32)
    values = values[np.isfinite(values)]
    if not values.size:
        return 1.0
    rank = int(round((values.size - 1) * percentile / 100))
    white = float(np.partition(values, rank)[rank])
    return white if white > 0 else 1.0


def to_codes(flux: NDArray, white: float) -> NDArray[np.uint8]:
    """Tone-map linear flux with a fixed white point to 8-bit sRGB (NaN -> 0, black).

    Args:
        flux: (H, W) float flux in photons/s, NaN where unobserved.
        white: flux mapped to 255 (see :func:`white_point`).

    Returns:
        (H, W) uint8 sRGB codes.
    """
    from .photons import linear_to_srgb

    scaled = np.nan_to_num(np.asarray(flux, np.float32), nan=0.0) / np.float32(white)
    return np.rint(linear_to_srgb(scaled) * 255).astype(np.uint8)


def _codec(av: Any, notes: list[str]) -> str:
    """``libx264`` if this PyAV build encodes with it, else the first H.264 or MPEG-4 encoder it has."""
    for name in ("libx264", "libopenh264", "mpeg4"):
        try:
            av.codec.Codec(name, "w")
        except Exception:  # noqa: BLE001 - PyAV raises its own errors for an unknown encoder
            continue
        if name != "libx264":
            notes.append(f"this PyAV build has no libx264 encoder: encoded with {name}")
        return name
    raise MissingDependency("this PyAV build has no H.264 or MPEG-4 encoder (libx264, libopenh264, mpeg4); "
                            "install PyAV from its wheels: pip install 'photonpano[video]'")


def _frame_size(shape: tuple[int, int], width: int | None, notes: list[str]) -> tuple[int, int] | None:
    """``(width, height)`` to resize to (even), or None to keep ``shape`` (padded to even sizes)."""
    height0, width0 = shape
    if width is None:
        if width0 <= MAX_DEFAULT_WIDTH:
            return None
        width = MAX_DEFAULT_WIDTH
        notes.append(f"the {width0}x{height0} frames are scaled to {width} pixels wide (--width to choose)")
    if width < 16:
        raise PhotonpanoError(f"--width must be at least 16 pixels, got {width}")
    width -= width % 2
    return width, max(2, round(height0 * width / width0 / 2) * 2)


def encode(path: Path, frames: Iterator[NDArray], count: int, *, fps: float, white: float,
           width: int | None = None, labels: Iterator[str] | None = None,
           advance: Callable[[int], None] | None = None) -> VideoInfo:
    """Tone-map ``count`` flux frames and encode them as an H.264 video at ``path`` (not atomic).

    Args:
        path: the file to write (``.mp4``; PyAV picks the container from the suffix).
        frames: ``count`` (H, W) float flux images in photons/s (NaN: black).
        count: frames to take from ``frames``.
        fps: playback frames per second (> 0).
        white: flux mapped to white (see :func:`white_point`).
        width: output width in pixels (height keeps the aspect; both even); None: the
            frames' own size (padded by a black row or column to even sizes), scaled
            down to :data:`MAX_DEFAULT_WIDTH` if wider.
        labels: a caption per frame drawn in its top-left corner, or None.
        advance: called with 1 after each frame (a progress bar).

    Returns:
        The :class:`VideoInfo`.

    Raises:
        MissingDependency: PyAV is not installed.
        PhotonpanoError: ``fps`` not positive, ``width`` too small, or the encoder fails.
    """
    import cv2

    av = require_av()
    if not fps > 0:
        raise PhotonpanoError(f"--fps must be positive, got {fps}")
    info = VideoInfo()
    info.codec = _codec(av, info.notes)
    stream = None
    try:
        with av.open(str(path), "w") as container:
            for flux in frames:
                if info.frames == count:
                    break
                if stream is None:
                    size = _frame_size(flux.shape, width, info.notes)
                    info.width, info.height = size or (flux.shape[1] + flux.shape[1] % 2,
                                                       flux.shape[0] + flux.shape[0] % 2)
                    stream = container.add_stream(info.codec, rate=Fraction(fps).limit_denominator(1000))
                    stream.width, stream.height, stream.pix_fmt = info.width, info.height, "yuv420p"
                    if info.codec == "libx264":
                        stream.options = {"crf": "18", "preset": "veryfast"}
                codes = to_codes(flux, white)
                if size is not None:
                    shrink = size[0] < codes.shape[1]
                    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
                    codes = np.asarray(cv2.resize(codes, size, interpolation=interpolation), np.uint8)  # no copy
                else:
                    codes = np.pad(codes, ((0, info.height - codes.shape[0]), (0, info.width - codes.shape[1])))
                if labels is not None:
                    text = next(labels)
                    cv2.putText(codes, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 0, 3, cv2.LINE_AA)
                    cv2.putText(codes, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 255, 1, cv2.LINE_AA)
                image = av.VideoFrame.from_ndarray(np.ascontiguousarray(codes), format="gray")
                for packet in stream.encode(image):
                    container.mux(packet)
                info.frames += 1
                if advance is not None:
                    advance(1)
            if stream is not None:
                for packet in stream.encode():
                    container.mux(packet)
    except (av.error.FFmpegError, ValueError) as exc:
        raise PhotonpanoError(f"cannot encode {path}: {exc}") from None
    return info
