"""Config fields shared by the sources that read a recorded capture (not plugins by themselves).

- :class:`CaptureConfig`: where the capture is and which frames to use (every file source);
- :class:`BinaryCaptureConfig`: the timing and read buffer of binary frames (``npy-cube``,
  ``swissspad-bin``);
- :class:`IntensityCaptureConfig`: the frame rate and camera response of intensity frames
  (``video``, ``photron-mraw``);
- :class:`ColourSourceConfig`: the colour panorama option's rules (``simulate`` and the
  SwissSPAD sources, whose sensors may carry colour filters).

A source redeclares a field (type, default, docstring) where it means more than here; the
field keeps its place in the spec reference, so every source lists ``path`` and the frame
range first.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Callable, ClassVar, Literal

from photonpano.errors import SourceError
from photonpano.stages import Compositor, SourceConfig
from pydantic import Field, model_validator

__all__ = ["CaptureConfig", "BinaryCaptureConfig", "IntensityCaptureConfig", "ColourSourceConfig"]


class CaptureConfig(SourceConfig):
    """Where a recorded capture is and which of its frames to use."""

    path: Path
    """The capture (each source says which files it reads)."""
    start: Annotated[int, Field(ge=0)] = 0
    """First frame to use."""
    stop: Annotated[int, Field(ge=1)] | None = None
    """One past the last frame to use (default: the end of the capture)."""

    def frame_range(self, total: int, where: object, unit: str = "frames") -> tuple[int, int]:
        """Return ``(start, stop)`` of the frames to use in a capture of ``total`` frames.

        Args:
            total: frames in the capture.
            where: the capture's name for the message (a path, say).
            unit: what ``total`` counts, for the message.

        Raises:
            SourceError: if ``start:stop`` is empty or reaches past the capture.
        """
        stop = total if self.stop is None else self.stop
        if not self.start < stop <= total:
            raise SourceError(f"source ({self.plugin}): frames {self.start}:{stop} are outside {where}, "
                              f"which holds {total} {unit}")
        return self.start, stop


class BinaryCaptureConfig(CaptureConfig):
    """A recorded capture of binary frames: its timing and the read buffer."""

    frame_rate_hz: Annotated[float, Field(gt=0)] = 100_000.0
    """Binary frames per second of the capture (SwissSPAD2: up to ~100 kHz)."""
    exposure_s: Annotated[float, Field(gt=0)] | None = None
    """Exposure time of one binary frame in seconds (default: 1 / frame_rate_hz)."""
    chunk_mb: Annotated[float, Field(gt=0)] = 32.0
    """Largest read buffer in MiB (bounds the memory used while streaming)."""


class IntensityCaptureConfig(CaptureConfig):
    """A recorded capture of intensity frames: its frame rate and camera response."""

    kind: ClassVar[str] = "intensity"  # frames are intensities: merge with ``mean``

    frame_rate_hz: Annotated[float, Field(gt=0)] | None = None
    """Frames per second (default: the recording's header)."""
    response: Literal["srgb", "gamma", "linear"] = "srgb"
    """How code values encode intensity: the sRGB curve (usual for exported video),
    ``value ** gamma``, or linear (raw sensor data)."""
    gamma: Annotated[float, Field(gt=0, le=5)] = 2.2
    """Exponent of the ``gamma`` response."""
    black_level: Annotated[float, Field(ge=0)] = 0.0
    """Code value of zero light."""
    white_level: Annotated[float, Field(gt=0)] | None = None
    """Code value of full scale (default: the largest code of the frames' bit depth)."""


class ColourSourceConfig(SourceConfig):
    """A source config whose sensor may carry colour filters: the colour panorama option's rules in one place.

    Subclasses define ``cfa`` (the colour-filter-array layout, None without filters) and
    ``colour_panorama`` (bool: also composite the colour planes).

    Raises:
        ValueError: (pydantic validation) ``colour_panorama`` without ``cfa``.
    """

    @model_validator(mode="after")
    def _colour_needs_cfa(self):
        if self.colour_panorama and self.cfa is None:
            raise ValueError("colour_panorama needs cfa (the colour filter array layout)")
        return self

    def panorama_compositor(self, build: Callable[[], Compositor]) -> Compositor:
        """The panorama stage's compositor (see :meth:`~photonpano.stages.SourceConfig.panorama_compositor`).

        With ``colour_panorama`` the panorama and its colour planes in one pass
        (:class:`~photonpano.plugins.compositors.colour.ColourPanorama` of ``build``); else ``build()``.
        """
        from photonpano.plugins.compositors.colour import ColourPanorama

        return ColourPanorama(build) if self.colour_panorama else build()
