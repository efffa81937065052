"""Intensity frames: conventional high-speed video alongside binary photon frames.

A high-speed camera (Photron FASTCAM/INFINICAM, any video) records *intensity* frames,
not bits. Sources of such captures subclass :class:`IntensitySource` (``kind =
"intensity"``): they decode frames a bounded chunk at a time, turn code values into
**linear intensity** with a response curve (:func:`response_lut`; sRGB or a gamma for
video files, linear for raw sensor data) and return float32 *sums* of linear intensity
over frame ranges. The ``mean`` merger and :func:`estimate_radiance` then divide by
the number of frames behind each pixel instead of applying the photon MLE.

Units: linear intensity is relative to the sensor's full scale, in [0, 1] (1 = the
white level of the response curve).
"""

from __future__ import annotations

import abc
import re
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from .stages import PhotonSource
from .streaming import sum_ranges_by_blocks

__all__ = [
    "Response",
    "response_lut",
    "IntensitySource",
    "mean_intensity",
    "estimate_radiance",
    "read_cih_frame_rate",
]

Response = Literal["linear", "srgb", "gamma"]
"""How code values encode intensity: ``linear``, the ``srgb`` curve or a power ``gamma``."""


def response_lut(response: Response, bits: int, *, gamma: float = 2.2, black_level: float = 0.0,
                 white_level: float | None = None) -> NDArray[np.float32]:
    """Return a lookup table from integer code values to linear intensity.

    The code value v is first normalised, ``u = clip((v - black_level) / (white_level -
    black_level), 0, 1)``, then decoded: ``linear`` keeps u, ``srgb`` undoes the sRGB
    curve (IEC 61966-2-1), ``gamma`` returns ``u ** gamma``.

    Args:
        response: the encoding of the code values.
        bits: code values are ``0 .. 2**bits - 1`` (8 for ordinary video, 12 or 16 for
            raw high-speed frames).
        gamma: exponent of the ``gamma`` response (display gamma, e.g. 2.2).
        black_level: code value of zero light.
        white_level: code value of full scale (default ``2**bits - 1``).

    Returns:
        (2**bits,) float32 linear intensities in [0, 1].

    Raises:
        ValueError: if ``white_level <= black_level`` or ``bits`` is not in 1..16.
    """
    from .photons import srgb_to_linear

    if not 1 <= bits <= 16:
        raise ValueError(f"bits must be in 1..16, got {bits}")
    top = float(2**bits - 1) if white_level is None else float(white_level)
    if top <= black_level:
        raise ValueError(f"white_level {top} must exceed black_level {black_level}")
    u = np.clip((np.arange(2**bits, dtype=np.float64) - black_level) / (top - black_level), 0, 1)
    if response == "srgb":
        return srgb_to_linear(u)
    if response == "gamma":
        return (u ** gamma).astype(np.float32)
    return u.astype(np.float32)


class IntensitySource(PhotonSource):
    """A capture of intensity frames, summed over frame ranges a chunk at a time.

    Subclasses set ``n_frames``, ``height``, ``width``, ``frame_rate_hz``,
    ``exposure_s``, ``name`` and ``lut`` (a :func:`response_lut`), and implement
    :meth:`read_codes`.

    Attributes:
        kind: ``"intensity"``.
        lut: (2**bits,) float32 code value -> linear intensity.
        chunk_frames: most frames decoded into memory at once.
    """

    kind = "intensity"
    lut: NDArray[np.float32]
    chunk_frames: int = 64

    @abc.abstractmethod
    def read_codes(self, start: int, stop: int) -> NDArray:
        """Decode frames ``start:stop`` as integer code values.

        Args:
            start: first frame, ``0 <= start < stop <= n_frames``.
            stop: one past the last frame.

        Returns:
            (stop - start, H, W) uint8 or uint16 code values (indices into ``lut``).
        """

    def read_frames(self, start: int, stop: int) -> NDArray[np.float32]:
        """Return frames ``start:stop`` as (K, H, W) float32 linear intensity in [0, 1]."""
        return self.lut[self.read_codes(start, stop)]

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.float32]:
        """Sum linear intensity over consecutive frame ranges.

        Frames are decoded at most ``chunk_frames`` at a time.

        Args:
            edges: (B + 1,) strictly increasing frame indices within ``[0, T]``.

        Returns:
            (B, H, W) float32 sums of linear intensity; range ``b`` covers frames
            ``edges[b]:edges[b+1]`` (divide by its length for the mean).

        Raises:
            ValueError: if the edges are not increasing or leave the capture.
        """
        def blocks(start: int, stop: int):
            for pos in range(start, stop, self.chunk_frames):
                yield pos, self.read_codes(pos, min(stop, pos + self.chunk_frames))

        def count(codes: NDArray, local: NDArray[np.int64]) -> NDArray[np.float32]:
            return np.stack([self.lut[codes[a:b]].sum(axis=0, dtype=np.float32)
                             for a, b in zip(local[:-1], local[1:])])

        return sum_ranges_by_blocks(edges, self.n_frames, blocks, count, (self.height, self.width), np.float32)


def mean_intensity(sums: NDArray, n_frames: NDArray | float, *, min_frames: float = 0.5) -> NDArray[np.float32]:
    """Mean linear intensity from warped sums.

    Args:
        sums: (H, W) accumulated linear intensity.
        n_frames: (H, W) or scalar number of frames behind each pixel.
        min_frames: pixels observed by fewer frames are NaN (unobserved).

    Returns:
        (H, W) float32 mean linear intensity (relative to full scale); NaN where unobserved.
    """
    s = np.asarray(sums, dtype=np.float32)
    n = np.broadcast_to(np.asarray(n_frames, dtype=np.float32), s.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n >= min_frames, s / np.maximum(n, 1e-12), np.nan).astype(np.float32)


def estimate_radiance(source: PhotonSource, sums: NDArray, n_frames: NDArray | float) -> NDArray[np.float32]:
    """Turn warped sums of a source's frames into its radiance estimate.

    Binary sources (``kind == "binary"``) get the flux MLE of paper Eq. (3) in
    photons/s; intensity sources get the mean linear intensity. This is the one call a
    panorama assembler needs to serve both kinds.

    Args:
        source: the capture (only ``kind`` and ``exposure_s`` are read).
        sums: (H, W) warped detection counts or intensity sums.
        n_frames: (H, W) or scalar frames behind each pixel.

    Returns:
        (H, W) float32 estimate; NaN where unobserved.
    """
    if getattr(source, "kind", "binary") == "intensity":
        return mean_intensity(sums, n_frames)
    from .photons import flux_mle

    return flux_mle(sums, n_frames, source.exposure_s)


_RATE_KEYS = re.compile(r"^\s*(frame\s*rate|framerate|record\s*rate(\(fps\))?|fps)\s*[:=]\s*([0-9.eE+]+)",
                        re.IGNORECASE)


def read_cih_frame_rate(path: Path) -> float | None:
    """Read the capture frame rate from a plain-text Photron ``.cih`` file.

    Accepts the INFINICAM ``framerate: 1000`` form and the FASTCAM ``Record
    Rate(fps) : 1000`` form (case-insensitive, ``:`` or ``=``).

    Args:
        path: the ``.cih`` file.

    Returns:
        Frames per second, or None if no such line is found.

    Raises:
        OSError: if the file cannot be read.
    """
    text = path.read_bytes().decode("utf-8", errors="replace")
    for line in text.splitlines():
        m = _RATE_KEYS.match(line)
        if m:
            try:
                value = float(m.group(3))
            except ValueError:
                continue
            if value > 0:
                return value
    return None
