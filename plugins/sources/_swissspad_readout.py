"""SwissSPAD2 raw readout files: layouts, bit order, decoding and encoding.

**Raw readout files** (``.bin``, no header, 8 MiB each, least significant bit first
within a byte, formats verified against the sensor authors' ``photoncube`` reader):

- ``half`` array: 512 frames of 256x512 pixels per file; each frame is 256 rows of
  64 bytes, pixel ``8 j + k`` of a row in bit ``k`` of byte ``j``.
- ``full`` array: 256 frames of 512x512 pixels per file; each frame is 256 readout
  records of 1024 pixels. Record ``r`` holds, in order, quarter-row ``q = 0..3``
  (columns ``128 q .. 128 q + 127``) of top-half row ``r`` and then of bottom-half
  row ``511 - r`` (the bottom half is read out flipped up-down).

Counts of raw frames are obtained by counting the stored bytes as if they were packed
most significant bit first (:func:`photonpano.photons.sum_packed_ranges`) and then
permuting the counts (:func:`record_counts_to_frame`): every layout step is a fixed
permutation of pixels, so it commutes with summing frames.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "BIN_FILE_BYTES",
    "RawLayout",
    "LAYOUTS",
    "Transform",
    "reverse_bits",
    "decode_frames",
    "encode_frames",
    "record_counts_to_frame",
    "write_bin_files",
    "list_bin_files",
    "layout_scores",
]

BIN_FILE_BYTES = 8 * 2**20
"""Size of one complete SwissSPAD2 raw readout file in bytes (8 MiB)."""


@dataclass(frozen=True)
class RawLayout:
    """How frames are laid out in SwissSPAD2 raw readout files.

    Attributes:
        name: ``"half"`` or ``"full"``.
        height: frame height in pixels.
        width: frame width in pixels.
        frames_per_file: frames in one complete 8 MiB file.
        record_shape: ``(rows, bytes)`` of one stored frame as counted, e.g.
            ``(256, 128)`` for the full array's 256 records of 1024 pixels.
    """

    name: str
    height: int
    width: int
    frames_per_file: int
    record_shape: tuple[int, int]

    @property
    def frame_bytes(self) -> int:
        """Bytes per stored frame (16 KiB half, 32 KiB full)."""
        return self.height * self.width // 8


LAYOUTS: dict[str, RawLayout] = {
    "half": RawLayout("half", 256, 512, 512, (256, 64)),
    "full": RawLayout("full", 512, 512, 256, (256, 128)),
}
"""The SwissSPAD2 readout layouts by name."""

Transform = Literal["rot90", "rot180", "rot270", "flip-ud", "flip-lr"]
"""A rotation or flip of corrected frames (``rot90``: 90 degrees clockwise as displayed)."""

_REVERSE = np.array([int(f"{v:08b}"[::-1], 2) for v in range(256)], dtype=np.uint8)


def reverse_bits(data: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Return ``data`` with the bit order of every byte reversed (LSB-first <-> MSB-first)."""
    return _REVERSE[data]


def decode_frames(raw: NDArray[np.uint8], layout: RawLayout) -> NDArray[np.uint8]:
    """Turn raw readout frames into bit-packed frames in the photonpano layout.

    Args:
        raw: (K, frame_bytes) or (K, *record_shape) uint8 bytes as stored in ``.bin``
            files (LSB first).
        layout: the readout layout.

    Returns:
        (K, H, W/8) uint8 frames bit-packed along the width, MSB first (exactly
        ``np.packbits(frames, axis=-1)``), in sensor row order.
    """
    k = len(raw)
    data = reverse_bits(np.asarray(raw, dtype=np.uint8).reshape(k, -1))
    if layout.name == "half":
        return data.reshape(k, layout.height, layout.width // 8)
    rec = data.reshape(k, 256, 4, 2, 16)  # record, quarter, top/bottom, 16 bytes = 128 px
    out = np.empty((k, 512, 64), dtype=np.uint8)
    out[:, :256] = rec[:, :, :, 0, :].reshape(k, 256, 64)
    out[:, 256:] = rec[:, ::-1, :, 1, :].reshape(k, 256, 64)
    return out


def encode_frames(packed: NDArray[np.uint8], layout: RawLayout) -> NDArray[np.uint8]:
    """Inverse of :func:`decode_frames`: bit-packed frames to raw readout bytes.

    Args:
        packed: (K, H, W/8) uint8 frames bit-packed MSB first; (H, W) must be the
            layout's (256x512 half, 512x512 full).
        layout: the readout layout.

    Returns:
        (K, frame_bytes) uint8 bytes exactly as the sensor stores them.

    Raises:
        ValueError: if the frame shape does not match the layout.
    """
    packed = np.asarray(packed, dtype=np.uint8)
    if packed.shape[1:] != (layout.height, layout.width // 8):
        raise ValueError(f"{layout.name} array frames are {layout.height}x{layout.width} "
                         f"(packed {layout.height}x{layout.width // 8}), got packed {packed.shape[1:]}")
    k = len(packed)
    if layout.name == "half":
        data = packed.reshape(k, -1)
    else:
        rec = np.empty((k, 256, 4, 2, 16), dtype=np.uint8)
        rec[:, :, :, 0, :] = packed[:, :256].reshape(k, 256, 4, 16)
        rec[:, :, :, 1, :] = packed[:, 256:][:, ::-1].reshape(k, 256, 4, 16)
        data = rec.reshape(k, -1)
    return reverse_bits(data)


def record_counts_to_frame(counts: NDArray, layout: RawLayout) -> NDArray:
    """Rearrange counts of raw records (counted MSB first) into sensor pixel order.

    Args:
        counts: (B, rows, 8 * bytes) counts of the stored bytes of ``layout.record_shape``,
            pixel ``8 j + k`` counting bit ``7 - k`` of byte ``j``.
        layout: the readout layout.

    Returns:
        (B, H, W) counts in sensor pixel order (a new array of the same dtype).
    """
    b = len(counts)
    # the files store bits LSB first: bit k of byte j is pixel 8 j + k
    lsb = np.asarray(counts).reshape(b, counts.shape[1], -1, 8)[..., ::-1].reshape(counts.shape)
    if layout.name == "half":
        return np.ascontiguousarray(lsb)
    rec = lsb.reshape(b, 256, 4, 2, 128)
    out = np.empty((b, 512, 512), dtype=counts.dtype)
    out[:, :256] = rec[:, :, :, 0, :].reshape(b, 256, 512)
    out[:, 256:] = rec[:, ::-1, :, 1, :].reshape(b, 256, 512)
    return out


def write_bin_files(packed: NDArray[np.uint8], folder: Path, layout: RawLayout | str = "half",
                    prefix: str = "RAW") -> list[Path]:
    """Write bit-packed frames as SwissSPAD2 raw readout files (for tests and simulations).

    Files are named ``{prefix}00000.bin``, ``{prefix}00001.bin``, ... and hold
    ``layout.frames_per_file`` frames each (the last one fewer if the frames run out).

    Args:
        packed: (T, H, W/8) uint8 frames bit-packed MSB first (a memory map is fine;
            it is written a file at a time).
        folder: output folder (created); existing files of the same name are refused.
        layout: ``"half"``/``"full"`` or a :class:`RawLayout`.
        prefix: file name prefix.

    Returns:
        The written paths in order.

    Raises:
        FileExistsError: if a file to write already exists.
        ValueError: if the frame shape does not match the layout.
    """
    layout = LAYOUTS[layout] if isinstance(layout, str) else layout
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    per = layout.frames_per_file
    for i, start in enumerate(range(0, len(packed), per)):
        path = folder / f"{prefix}{i:05d}.bin"
        with open(path, "xb") as f:
            f.write(encode_frames(packed[start:start + per], layout).tobytes())
        paths.append(path)
    return paths


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", str(path))]


def list_bin_files(folder: Path) -> list[Path]:
    """Return the ``.bin`` files under ``folder`` (recursively) in natural order.

    Natural order sorts ``RAW2.bin`` before ``RAW10.bin`` and equals the plain sorted
    order for zero-padded names (what the sensor software writes).
    """
    return sorted((p for p in folder.rglob("*") if p.suffix.lower() == ".bin" and p.is_file()),
                  key=lambda p: _natural_key(p.relative_to(folder)))


def bin_files(path: Path | list[Path], plugin: str, expected: str) -> tuple[list[Path], str]:
    """The ``.bin`` readout files a source's ``path`` names, and a label for messages.

    Args:
        path: a folder (its ``.bin`` files, :func:`list_bin_files`), one file, or a list of files.
        plugin: the source plugin's name, for messages.
        expected: what the files are, for the message of an empty folder.

    Returns:
        ``(files, label)``: the files in reading order and the folder's or file's name.

    Raises:
        SourceError: an empty list or folder, or a path that is not a file or folder.
    """
    from photonpano.errors import SourceError

    if isinstance(path, list):
        if not path:
            raise SourceError(f"source ({plugin}): the list of .bin files is empty")
        for p in path:
            if not p.is_file():
                raise SourceError(f"source ({plugin}): {p} does not exist or is not a file")
        return list(path), f"{len(path)} files"
    if path.is_dir():
        files = list_bin_files(path)
        if not files:
            raise SourceError(f"source ({plugin}): no .bin files in {path}; expected {expected}")
        return files, path.name
    if path.is_file():
        return [path], path.name
    raise SourceError(f"source ({plugin}): {path} does not exist")


def layout_scores(raw: NDArray[np.uint8]) -> dict[str, float]:
    """Measure how well raw readout frames fit each layout.

    The wrong layout puts quarter-rows of distant sensor regions side by side, so the
    mean image jumps at columns 128 and 384. The score of a layout is the mean
    absolute column step of the mean image (rows averaged in bands of 8) at those
    columns, divided by the median column step elsewhere: about 1 for the right layout, well above 1 for the wrong
    one when the scene has structure.

    Args:
        raw: (K, 16384 or 32768 * n) uint8 raw frames of one file, as stored; K * 16 KiB
            must be a whole number of full-array frames too (e.g. K even for half).

    Returns:
        ``{"half": score, "full": score}``.
    """
    flat = np.asarray(raw, dtype=np.uint8).reshape(-1)
    scores = {}
    for name, layout in LAYOUTS.items():
        k = len(flat) // layout.frame_bytes
        if k == 0:
            scores[name] = 1.0
            continue
        frames = decode_frames(flat[:k * layout.frame_bytes].reshape(k, -1), layout)
        mean = np.unpackbits(frames, axis=-1).mean(axis=0, dtype=np.float64)
        rows = len(mean) // 8 * 8
        mean = mean[:rows].reshape(-1, 8, mean.shape[1]).mean(axis=1)  # average 8 rows: less photon noise
        step = np.abs(np.diff(mean, axis=1)).mean(axis=0)  # (W - 1,) step between column c and c + 1
        boundary = step[[127, 383]].mean()
        others = np.delete(step, [127, 383])
        scores[name] = float(boundary / max(np.median(others), 1e-9))
    return scores
