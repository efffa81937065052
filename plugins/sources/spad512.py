"""Source ``spad512``: Pi Imaging SPAD512 (SPAD512S/SPAD512²) 1-bit readout files (``.bin``), streamed.

**Layout** (as the sensor authors' converter ``photoncube`` reads it, ``PhotonCube.convert_to_npy(...,
is_spad512=True)``): a capture is a folder of headerless ``.bin`` files in natural name order;
each complete file holds 1000 binary frames of 512x512 pixels, one bit per pixel, frames one
after the other, each frame row-major (512 rows of 64 bytes), pixel ``8 j + k`` of a row in
bit ``7 - k`` of byte ``j`` (most significant bit first: exactly ``np.packbits(frames,
axis=-1)``, the bits need no reversal, unlike SwissSPAD2 readouts). A complete default file
is 32 768 000 bytes. Frames stream in order across files; only the frames being merged are
read, a bounded chunk at a time. A truncated last file is reported (a warning, and
``describe()["notes"]``) and its whole frames used.

The frame size (``height``, ``width``), the bit order, the frames per file and a per-file
trailer are settings: by default the frames per file follow from the first file's size (a
whole number of frames, 1000 for the camera's default files), so files of 256 frames
(8 MiB) read unchanged; ``trailer_bytes: 4`` reads files with 4 bytes after their frames
(SPAD512S GUI 1-bit acquisitions as a public MATLAB reader, ``read_512Sbin.m`` by
D. Rodríguez, reads them: 256 frames and 4 trailing bytes). Hot/dead pixels are inpainted
with ``inpaint_mask`` and frames rotated or flipped with ``transforms``, as for the SwissSPAD
sources (:mod:`photonpano.plugins.sources._swissspad_sensor`).

``photonpano pano FOLDER`` picks this source over ``swissspad-bin`` when the first ``.bin``
file is a complete default SPAD512 file (32 768 000 bytes) or a SPAD512S GUI file
(8 388 612 bytes: 256 frames and a 4-byte trailer); SwissSPAD2 files are exactly 8 388 608
bytes. Other SPAD512 files need the source named in a spec (``plugin: spad512``).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.plugins.sources._capture_config import BinaryCaptureConfig
from photonpano.plugins.sources._swissspad_readout import Transform, bin_files
from photonpano.stages import PhotonSource, SourceConfig
from photonpano.streaming import ReopenOnPickle
from pydantic import Field

__all__ = ["Spad512Config", "Spad512", "SPAD512_FILE_BYTES", "SPAD512S_GUI_FILE_BYTES", "encode_spad512",
           "write_spad512_files", "Spad512Warning"]

SPAD512_FILE_BYTES = 1000 * 512 * 512 // 8
"""Size of one complete default SPAD512 readout file: 1000 frames of 512x512 bits (32 768 000 bytes)."""

SPAD512S_GUI_FILE_BYTES = 256 * 512 * 512 // 8 + 4
"""Size of one SPAD512S GUI 1-bit file: 256 frames of 512x512 bits and a 4-byte trailer (8 388 612 bytes)."""


class Spad512Warning(UserWarning):
    """A SPAD512 capture was read with a caveat (a truncated last file)."""


class Spad512Config(BinaryCaptureConfig):
    """Pi Imaging SPAD512 1-bit readouts: a folder or list of headerless ``.bin`` files."""

    plugin: Literal["spad512"] = "spad512"
    path: Path | list[Path]
    """A folder of ``.bin`` files (searched recursively, natural name order), one ``.bin``
    file, or a list of files in frame order."""
    height: Annotated[int, Field(gt=0)] = 512
    """Frame height in pixels (rows)."""
    width: Annotated[int, Field(gt=0, multiple_of=8)] = 512
    """Frame width in pixels (columns; a multiple of 8: rows are whole bytes)."""
    frames_per_file: Annotated[int, Field(gt=0)] | None = None
    """Binary frames in one complete file (the camera writes 1000). Default: from the size
    of the first file, which must then hold a whole number of frames (and the trailer).
    Set it to read a capture whose only file is truncated."""
    trailer_bytes: Annotated[int, Field(ge=0)] = 0
    """Bytes after the frames of each complete file, skipped (SPAD512S GUI 1-bit files: 4)."""
    bit_order: Literal["msb", "lsb"] = "msb"
    """Pixel order within a byte: ``msb`` (the camera's and ``photoncube``'s: pixel ``8 j``
    in the most significant bit of byte ``j``) or ``lsb`` (pixel ``8 j`` in the least
    significant bit)."""
    inpaint_mask: Path | None = None
    """Hot/dead pixels to inpaint: a bool ``.npy`` (True = inpaint) or an image (non-zero =
    inpaint) of at least ``height`` x ``width`` (a larger one is cropped to its top-left corner)."""
    transforms: list[Transform] = []
    """Rotations and flips applied in order after inpainting, e.g. ``[rot90]``."""

    def build(self) -> Spad512:
        """Index the files and check their sizes (reads no frames)."""
        return Spad512(self)



class Spad512(ReopenOnPickle, PhotonSource):
    """Pi Imaging SPAD512 1-bit readouts (see :class:`Spad512Config`).

    Pickles as its config (the files are indexed again where it is unpickled).

    Attributes:
        files: the readout files in frame order.
        frames_per_file: frames in one complete file.
        file_bytes: bytes of one complete file (frames and trailer).
        frames: the streaming reader (:class:`~photonpano.streaming.FrameFiles`) of all whole frames.
        corrector: the :class:`~photonpano.plugins.sources._swissspad_sensor.SensorCorrector`
            (inpainting, transforms) applied to counts.
        notes: caveats found while indexing (a truncated last file).
    """

    def __init__(self, config: Spad512Config) -> None:
        """Index the files.

        Raises:
            SourceError: no files, a file that is missing or unreadable, a first file that
                is not a whole number of frames (when ``frames_per_file`` is not set), a
                file of the wrong size (every file but the last must be complete), bad
                masks, or a frame range outside the capture; messages name the file and
                the size expected.
        """
        from photonpano.plugins.sources._swissspad_sensor import SensorCorrector, SwissSpadCorrections
        from photonpano.streaming import FrameFiles, FrameSegment

        self.config = config
        self.files, label = bin_files(config.path, "spad512", "SPAD512 readout files")
        fb = config.height * config.width // 8
        geometry = f"{config.height}x{config.width}"
        sizes = []
        for f in self.files:
            try:
                sizes.append(f.stat().st_size)
                with open(f, "rb"):
                    pass
            except OSError as exc:
                raise SourceError(f"source (spad512): cannot read {f} ({exc.strerror or exc})") from None
        trailer = config.trailer_bytes
        if config.frames_per_file is None:
            body = sizes[0] - trailer
            if body <= 0 or body % fb:
                raise SourceError(
                    f"source (spad512): {self.files[0]} is {sizes[0]} bytes, not a whole number of {geometry} "
                    f"1-bit frames ({fb} bytes each)" + (f" and a {trailer}-byte trailer" if trailer else "")
                    + f"; expected a SPAD512 readout file of {SPAD512_FILE_BYTES} bytes (1000 frames of 512x512); "
                    "set frames_per_file (a truncated file), trailer_bytes, height or width")
            self.frames_per_file = body // fb
        else:
            self.frames_per_file = config.frames_per_file
        self.file_bytes = self.frames_per_file * fb + trailer
        self.notes: list[str] = []
        segments = []
        for i, (f, size) in enumerate(zip(self.files, sizes)):
            last = i == len(self.files) - 1
            if size > self.file_bytes or (size != self.file_bytes and not last):
                raise SourceError(f"source (spad512): {f} is {size} bytes; expected a SPAD512 readout file of "
                                  f"{self.file_bytes} bytes ({self.frames_per_file} frames of {geometry}"
                                  + (f" and a {trailer}-byte trailer" if trailer else "") + ")"
                                  + ("" if last else "; only the last file may be truncated"))
            whole = self.frames_per_file if size == self.file_bytes else size // fb
            if size != self.file_bytes:
                note = (f"{f.name} is truncated ({size} of {self.file_bytes} bytes): using its {whole} whole "
                        f"frames, dropping {size - whole * fb} bytes")
                self.notes.append(note)
                warnings.warn(f"source (spad512): {note}", Spad512Warning, stacklevel=2)
            if whole:
                segments.append(FrameSegment(f, 0, whole))
        if not segments:
            raise SourceError(f"source (spad512): {self.files[0]} holds no whole {geometry} frame ({fb} bytes each)")
        self.frames = FrameFiles(segments, (config.height, config.width // 8), np.uint8,
                                 chunk_bytes=int(config.chunk_mb * 2**20))
        start, stop = config.frame_range(self.frames.n_frames, label, "whole frames")
        self.offset = start
        self.n_frames = stop - start
        # the corrections this source applies, as the settings SensorCorrector reads (not validated again)
        corrections = SwissSpadCorrections.model_construct(fix="none", inpaint_mask=config.inpaint_mask, cfa=None,
                                                           transforms=list(config.transforms))
        self.corrector = SensorCorrector(corrections, (config.height, config.width), None, f"spad512({label})")
        self.height, self.width = self.corrector.shape
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = config.exposure_s or 1.0 / config.frame_rate_hz
        self.name = f"spad512({label}, {len(self.files)} files, {geometry}, {self.frames_per_file} frames per file)"

    def read_frames(self, start: int, stop: int) -> NDArray[np.uint8]:
        """Read raw frames ``start:stop`` (no inpainting or transforms).

        Args:
            start: first frame (of this source's range).
            stop: one past the last frame.

        Returns:
            (K, height, width/8) uint8 frames bit-packed MSB first (``np.packbits`` layout),
            whatever the files' ``bit_order``.

        Raises:
            ValueError: if the range leaves the capture.
        """
        from photonpano.photons import check_frame_range
        from photonpano.plugins.sources._swissspad_readout import reverse_bits

        check_frame_range(start, stop, self.n_frames)
        raw = self.frames.read(self.offset + start, self.offset + stop)
        return reverse_bits(raw) if self.config.bit_order == "lsb" else raw

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges, corrected (see :meth:`PhotonSource.sum_ranges`)."""
        return self.corrector.apply(self.raw_sums(edges), np.asarray(edges, dtype=np.int64))

    def raw_sums(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges in sensor pixel order (no corrections).

        Args:
            edges: (B + 1,) strictly increasing frame indices within ``[0, n_frames]``.

        Returns:
            (B, height, width) uint16 counts.

        Raises:
            ValueError: if the edges are not increasing or leave the capture.
        """
        from photonpano.photons import check_frame_edges, sum_packed_ranges

        edges = check_frame_edges(edges, self.n_frames)
        h, w = self.config.height, self.config.width
        counts = self.frames.sum_ranges(edges + self.offset, sum_packed_ranges, (h, w))
        if self.config.bit_order == "lsb":  # stored bit k of byte j is pixel 8 j + k
            counts = np.ascontiguousarray(counts.reshape(len(counts), h, w // 8, 8)[..., ::-1].reshape(counts.shape))
        return counts

    def describe(self) -> dict[str, Any]:
        """Return the capture summary with the files, layout, corrections and notes."""
        c = self.config
        return {**super().describe(), "files": len(self.files), "first_file": str(self.files[0]),
                "frames_per_file": self.frames_per_file, "trailer_bytes": c.trailer_bytes,
                "bit_order": c.bit_order, "start": self.offset, "transforms": list(c.transforms),
                "notes": self.notes}


def encode_spad512(frames: NDArray, bit_order: Literal["msb", "lsb"] = "msb") -> bytes:
    """Encode binary frames as the bytes of a SPAD512 readout file (frames only, no trailer).

    Args:
        frames: (K, H, W) 0/1 or bool binary frames, W a multiple of 8.
        bit_order: ``msb`` (the camera's) or ``lsb``.

    Returns:
        ``K * H * W / 8`` bytes: frames in order, rows in order, 8 pixels per byte.

    Raises:
        ValueError: if ``frames`` is not 3-D or W is not a multiple of 8.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[2] % 8:
        raise ValueError(f"expected (K, H, W) binary frames with W a multiple of 8, got shape {frames.shape}")
    return np.packbits(frames.astype(bool), axis=-1, bitorder="big" if bit_order == "msb" else "little").tobytes()


def write_spad512_files(frames: NDArray, folder: Path, frames_per_file: int = 1000, *, trailer: bytes = b"",
                        bit_order: Literal["msb", "lsb"] = "msb", prefix: str = "spad512_") -> list[Path]:
    """Write binary frames as SPAD512 readout files (for tests and simulations).

    Files are named ``{prefix}00000.bin``, ``{prefix}00001.bin``, ... and hold
    ``frames_per_file`` frames each (the last one fewer if the frames run out) followed by
    ``trailer`` (complete files only).

    Args:
        frames: (T, H, W) 0/1 or bool binary frames (a memory map is fine; it is read a
            file at a time).
        folder: output folder (created); existing files of the same name are refused.
        frames_per_file: frames per complete file.
        trailer: bytes written after the frames of each complete file.
        bit_order: ``msb`` (the camera's) or ``lsb``.
        prefix: file name prefix.

    Returns:
        The written paths in order.

    Raises:
        FileExistsError: if a file to write already exists.
        ValueError: if the frames are not (T, H, W) with W a multiple of 8.
    """
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, start in enumerate(range(0, len(frames), frames_per_file)):
        path = folder / f"{prefix}{i:05d}.bin"
        chunk = frames[start:start + frames_per_file]
        with open(path, "xb") as f:
            f.write(encode_spad512(chunk, bit_order))
            if len(chunk) == frames_per_file:
                f.write(trailer)
        paths.append(path)
    return paths


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``spad512`` source."""
    return [Spad512Config]


@hookimpl(tryfirst=True)
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Claim a ``.bin`` file, or a folder whose first ``.bin`` file, has a SPAD512 file size.

    Called before ``swissspad-bin`` (which claims any ``.bin`` input): a complete default
    file (:data:`SPAD512_FILE_BYTES`) or a SPAD512S GUI file (:data:`SPAD512S_GUI_FILE_BYTES`,
    read with ``trailer_bytes: 4``) is a SPAD512 capture; any other size is left to other sources.
    """
    from photonpano.plugins.sources._swissspad_readout import list_bin_files

    if path.is_file() and path.suffix.lower() == ".bin":
        first: Path | None = path
    elif path.is_dir():
        files = list_bin_files(path)
        first = files[0] if files else None
    else:
        first = None
    if first is None:
        return None
    size = first.stat().st_size
    if size == SPAD512_FILE_BYTES:
        return {"plugin": "spad512", "path": str(path)}
    if size == SPAD512S_GUI_FILE_BYTES:
        return {"plugin": "spad512", "path": str(path), "trailer_bytes": 4}
    return None
