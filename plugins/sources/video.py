"""Source ``video``: high-speed video files and image-sequence folders, streamed.

Reads any video PyAV decodes (Photron INFINICAM MJPG AVI or MP4 exports, ...) or a
folder of images (PNG, TIFF, JPEG, BMP, PGM; natural name order). Frames are
intensities: they are converted to grey (the luma plane of video, OpenCV's grey
conversion of colour images), decoded to linear intensity with ``response`` (the sRGB
curve by default, as video is display-encoded) and summed over frame ranges a chunk at
a time (:class:`photonpano.intensity.IntensitySource`). Merge them with ``merger: mean``
(``photonpano pano`` picks it by itself).

The container frame rate of INFINICAM exports is a nominal 30 fps: the true capture
rate comes from ``frame_rate_hz`` or from the recording's plain-text ``.cih`` file next
to the video (``framerate: 1000`` or ``Record Rate(fps) : 1000``).

Video is decoded sequentially: the source indexes the packets once (no decoding), seeks
to the key frame before a requested range when it has to go back, and keeps recently
decoded frames in a bounded cache (``cache_mb``), so overlapping groups decode once.
"""

from __future__ import annotations

import re
import threading
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.intensity import IntensitySource, read_cih_frame_rate, response_lut
from photonpano.plugins.sources._capture_config import IntensityCaptureConfig
from photonpano.stages import SourceConfig
from photonpano.streaming import ReopenOnPickle
from pydantic import Field

__all__ = ["VideoConfig", "VideoSource", "VIDEO_SUFFIXES", "IMAGE_SUFFIXES", "find_cih"]

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".mjpg", ".mjpeg", ".wmv")
"""File suffixes ``photonpano pano`` reads with this source."""
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")
"""Image suffixes of image-sequence folders."""


class VideoConfig(IntensityCaptureConfig):
    """A high-speed video file (PyAV) or a folder of images, as intensity frames."""

    plugin: Literal["video"] = "video"
    requires = ("av",)
    install_hint = "pip install 'photonpano[video]'"

    path: Path
    """A video file, or a folder of images (one frame per image, natural name order)."""
    frame_rate_hz: Annotated[float, Field(gt=0)] | None = None
    """True capture rate in frames per second. Default: the ``framerate:`` line of the
    ``.cih`` file next to the video (``<name>.cih``, or the one ``.cih`` in an image
    folder); else the container's rate for a video (INFINICAM exports say a nominal
    30 fps) and an error for an image folder."""
    cih: Path | None = None
    """The recording's ``.cih`` file, if not next to the video under the same name."""
    white_level: Annotated[float, Field(gt=0)] | None = None
    """Code value of full scale (default: 255 for 8-bit, 65535 for 16-bit frames)."""
    exposure_s: Annotated[float, Field(gt=0)] | None = None
    """Exposure time of one frame in seconds (default: 1 / frame rate)."""
    cache_mb: Annotated[float, Field(gt=0)] = 256.0
    """Memory for recently decoded frames, in MiB."""
    strict: bool = False
    """Refuse a video whose readable frames differ in number from what its container
    announces (truncated or damaged file); default: a warning, also in ``run.json``."""

    def build(self) -> VideoSource:
        """Open the video (indexes its packets) or list the image folder."""
        return VideoSource(self)


def find_cih(path: Path) -> Path | None:
    """Return the ``.cih`` file of a recording, or None if absent.

    That is ``<name>.cih`` next to it, or the only ``.cih`` inside an image folder (or
    ``<folder>.cih`` next to it).
    """
    candidates = [path.with_suffix(".cih"), path.with_suffix(".CIH")]
    if path.is_dir():
        inside = sorted(p for p in path.iterdir() if p.suffix.lower() == ".cih")
        if len(inside) == 1:
            return inside[0]
        candidates = [path.parent / (path.name + ".cih")]
    return next((c for c in candidates if c.is_file()), None)


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


class _ImageFrames:
    """Frames of an image folder."""

    def __init__(self, folder: Path) -> None:
        import cv2

        self.files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                            key=_natural_key)
        if not self.files:
            raise SourceError(f"source (video): {folder} holds no images ({', '.join(IMAGE_SUFFIXES)}) "
                              "and is not a video")
        first = self._load(self.files[0], cv2)
        self.shape, self.dtype = first.shape, first.dtype
        self.n_frames = len(self.files)
        self.container_rate = None

    @staticmethod
    def _load(path: Path, cv2) -> NDArray:
        image = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
        if image is None:
            raise SourceError(f"source (video): {path} is not an image OpenCV can decode")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if image.dtype not in (np.uint8, np.uint16):
            raise SourceError(f"source (video): {path} has {image.dtype} pixels; expected 8- or 16-bit integers")
        return image

    def read(self, start: int, stop: int) -> NDArray:
        import cv2

        out = np.empty((stop - start,) + self.shape, self.dtype)
        for i in range(start, stop):
            image = self._load(self.files[i], cv2)
            if image.shape != self.shape or image.dtype != self.dtype:
                raise SourceError(f"source (video): {self.files[i]} is {image.shape} {image.dtype}; expected "
                                  f"{self.shape} {self.dtype} like {self.files[0].name}")
            out[i - start] = image
        return out


class _VideoFrames:
    """Frames of a video file decoded with PyAV, with seeking and a bounded cache."""

    def __init__(self, path: Path, cache_mb: float) -> None:
        import av

        self.path = path
        try:
            self.container = av.open(str(path))
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            raise SourceError(f"source (video): {path} is not a video PyAV can decode ({exc})") from None
        if not self.container.streams.video:
            raise SourceError(f"source (video): {path} has no video stream; expected a video file")
        self.stream = self.container.streams.video[0]
        self.stream.thread_type = "AUTO"
        pts, keys = [], []
        try:
            for packet in self.container.demux(self.stream):
                stamp = packet.pts if packet.pts is not None else packet.dts
                if stamp is None or packet.size == 0:
                    continue
                pts.append(stamp)
                keys.append(packet.is_keyframe)
        except av.error.FFmpegError as exc:
            raise SourceError(f"source (video): {path} is corrupt: cannot read its packets ({exc})") from None
        if not pts:
            raise SourceError(f"source (video): {path} holds no video frames")
        order = np.argsort(pts, kind="stable")
        self.pts = np.asarray(pts, dtype=np.int64)[order]
        self.keyframe = np.asarray(keys, bool)[order]
        self.index = {int(p): i for i, p in enumerate(self.pts)}
        self.n_frames = len(self.pts)
        self.announced = int(self.stream.frames or 0)  # the container's frame count, 0 if unknown
        rate = self.stream.average_rate or self.stream.guessed_rate
        self.container_rate = float(rate) if rate else None
        self._decoder = None
        self._next: int | None = None
        first = self._decode_range(0, 1)[0]
        self.shape, self.dtype = first.shape, first.dtype
        self.cache_frames = max(8, int(cache_mb * 2**20) // max(first.nbytes, 1))
        self.cache: OrderedDict[int, NDArray] = OrderedDict()
        self._decoder = None
        self._next = None
        self.lock = threading.Lock()

    def _frames_from(self, start: int):
        """Seek so that decoding yields frame ``start`` (and earlier frames, skipped)."""
        self.container.seek(int(self.pts[start]), stream=self.stream, backward=True, any_frame=False)
        return self.container.decode(self.stream)

    def _to_array(self, frame) -> NDArray:
        deep = any(b in frame.format.name for b in ("10", "12", "14", "16"))
        return frame.to_ndarray(format="gray16le" if deep else "gray")

    def _decode_range(self, start: int, stop: int) -> list[NDArray]:
        import av

        out: dict[int, NDArray] = {}
        decoder = self._decoder if self._next is not None and self._next <= start < self._next + 64 else None
        if decoder is None:
            decoder = self._frames_from(start)
        try:
            for frame in decoder:
                stamp = frame.pts if frame.pts is not None else frame.dts
                i = self.index.get(int(stamp)) if stamp is not None else None
                if i is None or i < start:
                    continue
                if i < stop:
                    out[i] = self._to_array(frame)
                    if hasattr(self, "cache"):  # not yet while probing the first frame
                        self._remember(i, out[i])
                if i >= stop - 1:
                    self._decoder, self._next = decoder, i + 1
                    break
        except av.error.FFmpegError as exc:
            raise SourceError(f"source (video): {self.path} is corrupt: decoding frame {start + len(out)} "
                              f"failed ({exc})") from None
        missing = [i for i in range(start, stop) if i not in out]
        if missing:
            raise SourceError(f"source (video): {self.path}: frame {missing[0]} could not be decoded "
                              f"(the file holds {self.n_frames} frame packets)")
        return [out[i] for i in range(start, stop)]

    def _remember(self, i: int, frame: NDArray) -> None:
        self.cache[i] = frame
        self.cache.move_to_end(i)
        while len(self.cache) > self.cache_frames:
            self.cache.popitem(last=False)

    def read(self, start: int, stop: int) -> NDArray:
        with self.lock:  # one decoder: threads take turns
            return self._read(start, stop)

    def _read(self, start: int, stop: int) -> NDArray:
        out = np.empty((stop - start,) + self.shape, self.dtype)
        i = start
        while i < stop:
            cached = self.cache.get(i)
            if cached is not None:
                out[i - start] = cached
                i += 1
                continue
            end = i
            while end < stop and end not in self.cache:
                end += 1
            for k, frame in enumerate(self._decode_range(i, end)):
                if frame.shape != self.shape:
                    raise SourceError(f"source (video): {self.path}: frame {i + k} is {frame.shape}; expected "
                                      f"{self.shape}")
                out[i + k - start] = frame
            i = end
        return out


class VideoSource(ReopenOnPickle, IntensitySource):
    """A video or image sequence as intensity frames (see :class:`VideoConfig`).

    Attributes:
        frames: the frame reader (video decoder or image list).
        cih: the ``.cih`` file the frame rate came from, or None.
        frame_rate_source: ``"config"``, ``"cih"`` or ``"container"``.
    """

    def __init__(self, config: VideoConfig) -> None:
        """Open the capture.

        Raises:
            SourceError: missing or undecodable file, no frames, an unreadable
                ``.cih``, no frame rate for an image folder, or frames outside the
                capture; messages name the file.
        """
        self.config = config
        path = config.path
        if not path.exists():
            raise SourceError(f"source (video): {path} does not exist")
        self.frames = _ImageFrames(path) if path.is_dir() else _VideoFrames(path, config.cache_mb)
        self.notes: list[str] = []
        announced = getattr(self.frames, "announced", 0)
        if announced and announced != self.frames.n_frames:
            note = (f"source (video): {path}: the container announces {announced} frames but "
                    f"{self.frames.n_frames} can be read (truncated or damaged file)")
            if config.strict:
                raise SourceError(note + "; strict: true refuses it")
            warnings.warn(note, stacklevel=2)
            self.notes.append(note)
        cih = config.cih if config.cih is not None else find_cih(path)
        self.cih = cih
        if config.frame_rate_hz is not None:
            rate, how = config.frame_rate_hz, "config"
        else:
            rate, how = None, ""
            if cih is not None:
                try:
                    rate = read_cih_frame_rate(cih)
                except OSError as exc:
                    raise SourceError(f"source (video): cannot read {cih} ({exc.strerror or exc})") from None
                if rate is None:
                    raise SourceError(f"source (video): {cih} has no frame rate line; expected e.g. "
                                      "'framerate: 1000' (or set frame_rate_hz)")
                how = "cih"
            elif self.frames.container_rate:
                rate, how = self.frames.container_rate, "container"
            else:
                raise SourceError(f"source (video): no frame rate for {path}: set frame_rate_hz or put the "
                                  "recording's .cih file next to it")
        assert rate is not None  # each branch above sets it or raises
        self.frame_rate_hz, self.frame_rate_source = float(rate), how
        self.exposure_s = config.exposure_s or 1.0 / self.frame_rate_hz
        start, stop = config.frame_range(self.frames.n_frames, path)
        self.offset, self.n_frames = start, stop - start
        self.height, self.width = self.frames.shape
        bits = 8 if self.frames.dtype == np.uint8 else 16
        self.lut = response_lut(config.response, bits, gamma=config.gamma, black_level=config.black_level,
                                white_level=config.white_level)
        kind = "images" if path.is_dir() else path.suffix.lstrip(".").lower()
        self.name = f"video({path.name}, {kind}, {self.frame_rate_hz:g} fps from {how})"

    def read_codes(self, start: int, stop: int) -> NDArray:
        """Decode frames ``start:stop`` as (K, H, W) uint8/uint16 grey code values."""
        return self.frames.read(self.offset + start, self.offset + stop)

    def describe(self) -> dict[str, Any]:
        """Return the capture summary with the frame rate's origin and the response."""
        return {**super().describe(), "path": str(self.config.path), "start": self.offset,
                "frame_rate_from": self.frame_rate_source, "cih": str(self.cih) if self.cih else None,
                "response": self.config.response, "warnings": self.notes}



@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``video`` source."""
    return [VideoConfig]


@hookimpl
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Read video files and folders of images with this source."""
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        return {"plugin": "video", "path": str(path)}
    if path.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
        return {"plugin": "video", "path": str(path)}
    return None
