"""Source ``photron-mraw``: Photron FASTCAM ``.mraw`` recordings with a ``.cih``/``.cihx`` header.

The header is read with the ``pyMRAW`` package (LADISK): frame count, size, frame
rate, shutter, storage bit depth (8, 12 bit-packed or 16) and the effective bit depth
and side. Frames are read a bounded chunk at a time with plain file reads (12-bit
chunks unpacked with the same bit layout as ``pyMRAW``'s decoder), never the whole
recording: pyMRAW's own ``load_video`` would unpack a 12-bit file into memory at once.

Values are linear sensor data: the default ``response`` is ``linear`` with the white
level of the effective bit depth (4095 for 12 effective bits). Colour cameras store raw
Bayer data; it is read as grey. Merge with ``merger: mean`` (``photonpano pano`` picks it).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.intensity import IntensitySource, response_lut
from photonpano.plugins.sources._capture_config import IntensityCaptureConfig
from photonpano.stages import SourceConfig
from photonpano.streaming import ReopenOnPickle
from pydantic import Field

__all__ = ["PhotronMrawConfig", "PhotronMraw", "header_and_data", "unpack_uint12"]


class PhotronMrawConfig(IntensityCaptureConfig):
    """A Photron FASTCAM ``.mraw`` recording and its ``.cih``/``.cihx`` header (pyMRAW)."""

    plugin: Literal["photron-mraw"] = "photron-mraw"
    requires = ("pyMRAW",)
    install_hint = "pip install 'photonpano[mraw]'"

    path: Path
    """The ``.mraw`` file, or its ``.cihx``/``.cih`` header (the other file has the same
    name next to it)."""
    frame_rate_hz: Annotated[float, Field(gt=0)] | None = None
    """Frames per second (default: the header's record rate)."""
    response: Literal["linear", "srgb", "gamma"] = "linear"
    """How code values encode intensity (raw FASTCAM data is linear)."""
    black_level: Annotated[float, Field(ge=0)] = 0.0
    """Code value of zero light (after shifting ``Higher``-side data down)."""
    white_level: Annotated[float, Field(gt=0)] | None = None
    """Code value of full scale (default: 2**effective_bits - 1)."""
    chunk_mb: Annotated[float, Field(gt=0)] = 32.0
    """Largest read buffer in MiB."""

    def build(self) -> PhotronMraw:
        """Read the header and check the data file's size."""
        return PhotronMraw(self)


def header_and_data(path: Path) -> tuple[Path, Path]:
    """Return ``(header, mraw)`` for a ``.mraw`` or ``.cih``/``.cihx`` path.

    Raises:
        SourceError: if either file is missing.
    """
    suffix = path.suffix.lower()
    header: Path | None
    if suffix in (".cih", ".cihx"):
        header, mraw = path, path.with_suffix(".mraw")
    else:
        mraw = path
        header = next((c for c in (path.with_suffix(".cihx"), path.with_suffix(".cih")) if c.is_file()), None)
        if header is None:
            raise SourceError(f"source (photron-mraw): no header for {path}; expected {path.with_suffix('.cihx').name}"
                              f" or {path.with_suffix('.cih').name} next to it")
    for f in (header, mraw):
        if not f.is_file():
            raise SourceError(f"source (photron-mraw): {f} does not exist")
    return header, mraw


def _exposure(value: Any) -> float | None:
    """Photron shutter values are 1/s (e.g. 50000 for 1/50000 s) or fractions '1/50000'."""
    try:
        if isinstance(value, str) and "/" in value:
            num, den = value.split("/", 1)
            return float(num) / float(den)
        v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    if v <= 0:
        return None
    return 1.0 / v if v > 1 else v


def unpack_uint12(data: NDArray[np.uint8]) -> NDArray[np.uint16]:
    """Unpack Photron 12-bit packed pixels: 3 bytes hold two values, big-endian nibbles.

    Bytes ``a, b, c`` give ``(a << 4) | (b >> 4)`` and ``((b & 15) << 8) | c``, the
    layout pyMRAW's ``nb_read_uint12`` decodes (that function runs on a numba parallel
    pool, which is not safe to call from the pipeline's worker threads, hence this
    NumPy version; the tests check both agree).

    Args:
        data: (..., 3 n) uint8 packed bytes.

    Returns:
        (2 n * ...,) flat uint16 values.
    """
    triples = np.asarray(data, dtype=np.uint8).reshape(-1, 3).astype(np.uint16)
    out = np.empty((len(triples), 2), np.uint16)
    out[:, 0] = (triples[:, 0] << 4) | (triples[:, 1] >> 4)
    out[:, 1] = ((triples[:, 1] & 15) << 8) | triples[:, 2]
    return out.reshape(-1)


class PhotronMraw(ReopenOnPickle, IntensitySource):
    """A Photron ``.mraw`` recording as intensity frames (see :class:`PhotronMrawConfig`).

    Attributes:
        header: the parsed header (pyMRAW's dict).
        bits: storage bits per pixel (8, 12 or 16).
        effective_bits: bits that carry data.
    """

    def __init__(self, config: PhotronMrawConfig) -> None:
        """Read the header.

        Raises:
            SourceError: missing files, an unreadable header, an unsupported bit depth,
                or a data file whose size does not match the header; messages name the file.
        """
        import pyMRAW
        from photonpano.streaming import FrameFiles, FrameSegment

        self.config = config
        header_path, mraw = header_and_data(config.path)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cih = pyMRAW.get_cih(str(header_path))
                pyMRAW.check_exceptions(cih)
            n, h, w = int(cih["Total Frame"]), int(cih["Image Height"]), int(cih["Image Width"])
            bits, eff = int(cih["Color Bit"]), int(cih["EffectiveBit Depth"])
            side = str(cih["EffectiveBit Side"]).lower()
        except Exception as exc:  # pyMRAW raises bare Exceptions, KeyErrors, XML errors
            raise SourceError(f"source (photron-mraw): {header_path} is not a readable Photron header "
                              f"({type(exc).__name__}: {exc})") from None
        if min(n, h, w) <= 0:
            raise SourceError(f"source (photron-mraw): {header_path} declares {n} frames of {w}x{h} pixels; "
                              "expected positive sizes (damaged header)")
        if str(cih.get("File Format", "mraw")).lower() != "mraw" or bits not in (8, 12, 16):
            raise SourceError(f"source (photron-mraw): {header_path} describes {cih.get('File Format')} data of "
                              f"{bits} bits; expected MRAW with 8, 12 or 16 bits per pixel")
        if bits == 12 and (h * w) % 2:
            raise SourceError(f"source (photron-mraw): {header_path}: 12-bit frames of {w}x{h} (odd pixel count) "
                              "are not supported")
        frame_bytes = h * w * bits // 8
        size = mraw.stat().st_size
        if size < n * frame_bytes:
            raise SourceError(f"source (photron-mraw): {mraw} is {size} bytes; expected {n} frames of {w}x{h} at "
                              f"{bits} bits = {n * frame_bytes} bytes (truncated or wrong header)")
        self.header, self.bits, self.effective_bits = cih, bits, eff
        self.shift = max(bits - eff, 0) if side == "higher" and bits != 8 else 0
        frame_dtype = np.dtype("<u2") if bits == 16 else np.uint8
        shape, dtype = ((frame_bytes,), np.uint8) if bits == 12 else ((h, w), frame_dtype)
        self.frames = FrameFiles([FrameSegment(mraw, 0, n)], shape, dtype, chunk_bytes=int(config.chunk_mb * 2**20))
        self.chunk_frames = max(1, min(self.frames.chunk_frames, 64))
        start, stop = config.frame_range(n, mraw)
        self.offset, self.n_frames = start, stop - start
        self.height, self.width = h, w
        rate = config.frame_rate_hz or float(cih.get("Record Rate(fps)") or 0)
        if not rate > 0:
            raise SourceError(f"source (photron-mraw): {header_path} gives no record rate; set frame_rate_hz")
        self.frame_rate_hz = rate
        self.exposure_s = _exposure(cih.get("Shutter Speed(s)")) or 1.0 / rate
        white = config.white_level if config.white_level is not None else float(2**min(eff, bits) - 1)
        self.lut = response_lut(config.response, 8 if bits == 8 else 16, gamma=config.gamma,
                                black_level=config.black_level, white_level=white)
        self.name = (f"photron-mraw({mraw.name}, {cih.get('Camera Type', '?')}, {bits}-bit, "
                     f"{rate:g} fps)")

    def read_codes(self, start: int, stop: int) -> NDArray:
        """Read frames ``start:stop`` as (K, H, W) uint8/uint16 code values."""
        raw = self.frames.read(self.offset + start, self.offset + stop)
        if self.bits == 12:
            codes = unpack_uint12(raw).reshape(stop - start, self.height, self.width)
        else:
            codes = raw
        if self.bits == 16:
            codes = codes.astype(np.uint16, copy=False)
        return codes >> self.shift if self.shift else codes

    def describe(self) -> dict[str, Any]:
        """Return the capture summary with the header's camera, bit depths and path."""
        return {**super().describe(), "path": str(self.config.path), "start": self.offset,
                "camera": self.header.get("Camera Type"), "bits": self.bits,
                "effective_bits": self.effective_bits}


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``photron-mraw`` source."""
    return [PhotronMrawConfig]


@hookimpl
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Read ``.mraw`` files (and ``.cihx``/``.cih`` headers next to one) with this source."""
    suffix = path.suffix.lower()
    if suffix == ".mraw" or (suffix in (".cih", ".cihx") and path.with_suffix(".mraw").is_file()):
        return {"plugin": "photron-mraw", "path": str(path)}
    return None
