"""Source ``swissspad-bin``: SwissSPAD2 raw readout files (``.bin``), streamed.

A capture is a folder (searched recursively, natural file-name order) or a list of
headerless 8 MiB readout files, least significant bit first: 512 frames of 256x512 per
file for the half array, 256 frames of 512x512 for the full array (see
:mod:`photonpano.plugins.sources._swissspad_readout` for the exact layouts). Frames stream in order across files;
only the frames being merged are read, a bounded chunk at a time. A truncated last
file is reported (a warning, and ``describe()["notes"]``) and its whole frames used.

The sensor corrections (``fix``, ``inpaint_mask``, ``cfa``, ``transforms``) are shared
with ``npy-cube``. ``photonpano convert`` turns readouts into a bit-packed ``.npy``
cube (:func:`convert_bin_to_npy`).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.plugins.sources._capture_config import BinaryCaptureConfig
from photonpano.plugins.sources._swissspad_readout import BIN_FILE_BYTES, LAYOUTS, bin_files
from photonpano.plugins.sources._swissspad_sensor import SwissSpadCorrections
from photonpano.stages import PhotonSource, SourceConfig
from photonpano.streaming import ReopenOnPickle, write_npy_blocks

__all__ = ["SwissSpadBinConfig", "SwissSpadBin", "convert_bin_to_npy", "SourceWarning"]


class SourceWarning(UserWarning):
    """A capture was read with a caveat (e.g. a truncated last file)."""


class SwissSpadBinConfig(SwissSpadCorrections, BinaryCaptureConfig):
    """SwissSPAD2 raw readouts: a folder or list of headerless 8 MiB ``.bin`` files."""

    plugin: Literal["swissspad-bin"] = "swissspad-bin"
    path: Path | list[Path]
    """A folder of ``.bin`` files (searched recursively, natural name order), one
    ``.bin`` file, or a list of files in frame order."""
    layout: Literal["half", "full"] = "half"
    """``half``: 512 frames of 256x512 per file; ``full``: 256 frames of 512x512 per
    file (quarter-row records alternating top half and flipped bottom half)."""
    check_layout: bool = True
    """Refuse a layout whose decoded frames show the seams of the other layout (sharp
    steps at columns 128 and 384 of the mean image of the first file)."""

    def build(self) -> SwissSpadBin:
        """Index the files and check their sizes and layout (reads one file's worth)."""
        return SwissSpadBin(self)



class SwissSpadBin(ReopenOnPickle, PhotonSource):
    """SwissSPAD2 raw readouts (see :class:`SwissSpadBinConfig`).

    Attributes:
        files: the readout files in frame order.
        layout: the :class:`~photonpano.plugins.sources._swissspad_readout.RawLayout`.
        corrector: the :class:`~photonpano.plugins.sources._swissspad_sensor.SensorCorrector` applied to counts.
        notes: caveats found while indexing (a truncated last file).
    """

    def __init__(self, config: SwissSpadBinConfig) -> None:
        """Index the files.

        Raises:
            SourceError: no files, a file that is missing, unreadable, of the wrong size
                (every file but the last must be 8 MiB), a layout that does not fit
                the data, or a frame range outside the capture; messages name the file.
        """
        from photonpano.plugins.sources._swissspad_sensor import SensorCorrector
        from photonpano.streaming import FrameFiles, FrameSegment

        self.config = config
        self.layout = LAYOUTS[config.layout]
        self.files, label = bin_files(config.path, "swissspad-bin", "SwissSPAD2 raw readout files")
        self.notes: list[str] = []
        segments = []
        fb = self.layout.frame_bytes
        for i, f in enumerate(self.files):
            try:
                size = f.stat().st_size
                with open(f, "rb"):
                    pass
            except OSError as exc:
                raise SourceError(f"source (swissspad-bin): cannot read {f} ({exc.strerror or exc})") from None
            last = i == len(self.files) - 1
            if size > BIN_FILE_BYTES or (size != BIN_FILE_BYTES and not last):
                raise SourceError(f"source (swissspad-bin): {f} is {size} bytes; expected a SwissSPAD2 raw "
                                  f"readout file of {BIN_FILE_BYTES} bytes (8 MiB, {self.layout.frames_per_file} "
                                  f"{self.layout.name}-array frames)"
                                  + ("" if last else "; only the last file may be truncated"))
            whole = size // fb
            if size != BIN_FILE_BYTES:
                note = (f"{f.name} is truncated ({size} of {BIN_FILE_BYTES} bytes): using its {whole} whole "
                        f"frames, dropping {size - whole * fb} bytes")
                self.notes.append(note)
                warnings.warn(f"source (swissspad-bin): {note}", SourceWarning, stacklevel=2)
            if whole:
                segments.append(FrameSegment(f, 0, whole))
        if not segments:
            raise SourceError(f"source (swissspad-bin): {self.files[0]} holds no whole {self.layout.name}-array "
                              f"frame ({fb} bytes each)")
        self.frames = FrameFiles(segments, self.layout.record_shape, np.uint8,
                                 chunk_bytes=int(config.chunk_mb * 2**20))
        if config.check_layout:
            self._check_layout(segments[0])
        start, stop = config.frame_range(self.frames.n_frames, label, "whole frames")
        self.offset = start
        self.n_frames = stop - start
        self.corrector = SensorCorrector(config, (self.layout.height, self.layout.width), self.layout.name,
                                         f"swissspad-bin({label})")
        self.height, self.width = self.corrector.shape
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = config.exposure_s or 1.0 / config.frame_rate_hz
        self.name = f"swissspad-bin({label}, {len(self.files)} files, {self.layout.name} array, fix {config.fix})"

    def _check_layout(self, first) -> None:
        from photonpano.plugins.sources._swissspad_readout import layout_scores

        n_bytes = min(first.n_frames * self.layout.frame_bytes, BIN_FILE_BYTES)
        n_bytes -= n_bytes % LAYOUTS["full"].frame_bytes
        if n_bytes == 0:
            return
        with open(first.path, "rb") as f:
            raw = np.frombuffer(f.read(n_bytes), dtype=np.uint8)
        scores = layout_scores(raw)
        chosen, other = self.layout.name, "full" if self.layout.name == "half" else "half"
        if scores[chosen] > 3.0 and scores[other] * 3.0 < scores[chosen]:
            raise SourceError(f"source (swissspad-bin): {first.path} does not look like {chosen}-array readouts "
                              f"(seams at columns 128/384 score {scores[chosen]:.1f}, {scores[other]:.1f} as "
                              f"{other} array); expected layout: {other} (or set check_layout: false)")

    def read_frames(self, start: int, stop: int) -> NDArray[np.uint8]:
        """Read raw frames ``start:stop`` (uncorrected, sensor pixel order).

        Args:
            start: first frame (of this source's range).
            stop: one past the last frame.

        Returns:
            (K, H_raw, W_raw/8) uint8 frames bit-packed MSB first (``np.packbits`` layout).
        """
        from photonpano.photons import check_frame_range
        from photonpano.plugins.sources._swissspad_readout import decode_frames

        check_frame_range(start, stop, self.n_frames)
        raw = self.frames.read(self.offset + start, self.offset + stop)
        return decode_frames(raw, self.layout)

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges, corrected (see :meth:`PhotonSource.sum_ranges`)."""
        return self.corrector.apply(self.raw_sums(edges), np.asarray(edges, dtype=np.int64))

    def raw_sums(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges in raw sensor pixel order (no corrections).

        Args:
            edges: (B + 1,) strictly increasing frame indices within ``[0, n_frames]``.

        Returns:
            (B, H_raw, W_raw) uint16 counts.
        """
        from photonpano.photons import check_frame_edges, sum_packed_ranges
        from photonpano.plugins.sources._swissspad_readout import record_counts_to_frame

        edges = check_frame_edges(edges, self.n_frames)
        rows, nbytes = self.layout.record_shape
        counts = self.frames.sum_ranges(edges + self.offset, sum_packed_ranges, (rows, nbytes * 8))
        return record_counts_to_frame(counts, self.layout)

    def describe(self) -> dict[str, Any]:
        """Return the capture summary with the files, layout, corrections and notes."""
        c = self.config
        return {**super().describe(), "files": len(self.files), "first_file": str(self.files[0]),
                "layout": self.layout.name, "start": self.offset, "fix": c.fix,
                "transforms": list(c.transforms), "notes": self.notes}


def convert_bin_to_npy(inputs: list[Path], output: Path, layout: str = "half", *,
                       progress: Callable[[int, int], None] | None = None,
                       chunk_mb: float = 32.0, check_layout: bool = True,
                       restart: bool = False) -> tuple[int, list[str]]:
    """Convert SwissSPAD2 raw readouts into a bit-packed ``.npy`` photon cube, streaming.

    The cube holds the raw frames in sensor pixel order, ``(T, 256, 64)`` (half) or
    ``(T, 512, 64)`` (full) uint8 packed MSB first, exactly what
    ``photoncube.PhotonCube.convert_to_npy`` writes; sensor corrections are applied
    when the cube is read (``npy-cube`` with ``fix``, ``inpaint_mask``, ...). Memory use
    is one read buffer (``chunk_mb``), whatever the capture length. The file is written
    under a temporary name and renamed when complete.

    Args:
        inputs: one folder of ``.bin`` files, or ``.bin`` files in frame order.
        output: the ``.npy`` file to write (must not exist).
        layout: ``"half"`` or ``"full"``.
        progress: called as ``progress(frames_done, total_frames)``.
        chunk_mb: read buffer in MiB.
        check_layout: refuse a layout that does not fit the data.
        restart: remove the ``.part`` left by an interrupted conversion first (see
            :func:`photonpano.outputs.partial.claim_partial`).

    Returns:
        ``(frames, notes)``: frames written and caveats (a truncated last file).

    Raises:
        SourceError: bad inputs (see :class:`SwissSpadBin`) or an existing output.
        OutputError: ``output`` or ``<output>.part`` is a symbolic link, the ``.part``
            file exists (never written through, never removed), or the disk is full
            (see :func:`photonpano.streaming.write_npy_blocks`).
    """
    path: Path | list[Path] = inputs[0] if len(inputs) == 1 and inputs[0].is_dir() else list(inputs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SourceWarning)
        source = SwissSpadBinConfig(path=path, layout=layout, chunk_mb=chunk_mb, check_layout=check_layout).build()
    if output.exists() or output.is_symlink():
        raise SourceError(f"convert: {output} exists; refusing to overwrite it")
    lay = source.layout
    step = source.frames.chunk_frames
    write_npy_blocks(output, (source.n_frames, lay.height, lay.width // 8), np.uint8,
                     (source.read_frames(start, min(start + step, source.n_frames))
                      for start in range(0, source.n_frames, step)), progress, restart)
    return source.n_frames, source.notes


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``swissspad-bin`` source."""
    return [SwissSpadBinConfig]


@hookimpl
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Read a ``.bin`` file, or a folder holding ``.bin`` files, with this source."""
    if path.is_file() and path.suffix.lower() == ".bin":
        return {"plugin": "swissspad-bin", "path": str(path)}
    if path.is_dir() and next((p for p in path.rglob("*") if p.suffix.lower() == ".bin"), None) is not None:
        return {"plugin": "swissspad-bin", "path": str(path)}
    return None
