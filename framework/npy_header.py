"""Check an ``.npy`` file's header against the file before anything is allocated.

``np.load`` trusts the header: a negative dimension, or a shape that claims 10^12
frames in a small file, ends in a deep traceback or a petabyte allocation attempt.
:func:`check_npy` reads only the header (NumPy's own parser, no unpickling) and checks
that the dimensions are non-negative and that the file holds exactly the bytes they
describe, as data rather than holes: a sparse file whose header declares 10^8 frames
has the right length but no data, and reading it would take hours.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .errors import SourceError

__all__ = ["check_npy", "load_npy", "data_bytes", "SPARSE_SLACK", "BYTES_PER_FRAME", "check_frames_fit_memory",
           "available_memory"]

BYTES_PER_FRAME = 256
"""A lower bound of the memory a run keeps per binary frame (its (3, 3) float64 homography,
72 bytes, and the working copies of the interpolation, the guards and the compositor)."""

SPARSE_SLACK = 64 * 2**20
"""Holes (bytes never written) an ``.npy`` file may have before it is refused as sparse (64 MiB);
past that, more than half the declared data must be stored."""


def check_npy(path: Path, what: str) -> tuple[tuple[int, ...], np.dtype, bool]:
    """Read and check the header of the ``.npy`` file ``path``.

    Args:
        path: the file.
        what: how messages name it (e.g. ``"source (npy-cube)"``).

    Returns:
        ``(shape, dtype, fortran_order)`` as the header declares them.

    Raises:
        SourceError: unreadable file or header, object dtype, a negative dimension, a
            file smaller than the header describes (truncated, or a header claiming more
            data than the file holds), or a sparse file whose holes are more than half the
            declared data and over :data:`SPARSE_SLACK`; one line naming ``path``, the
            declared and the real size.
    """
    fmt = np.lib.format
    try:
        with open(path, "rb") as handle:
            version = fmt.read_magic(handle)
            reader = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
            if reader is None:
                raise ValueError(f"unsupported .npy format version {version}")
            shape, fortran, dtype = reader(handle, max_header_size=100_000)
            offset = handle.tell()
    except Exception as exc:  # the header parser raises ValueError, SyntaxError, TokenError, ...
        message = " ".join(str(exc).split())[:160]
        raise SourceError(f"{what}: {path} is not a readable .npy file ({message})") from None
    if dtype.hasobject:
        raise SourceError(f"{what}: {path} holds Python objects; expected numbers (no pickles are loaded)")
    if any(int(d) < 0 for d in shape):
        raise SourceError(f"{what}: {path}: its header declares a negative dimension {tuple(shape)}")
    expected = int(np.prod(shape, dtype=object)) * dtype.itemsize
    actual = path.stat().st_size - offset
    if actual < expected:
        raise SourceError(f"{what}: {path} is truncated: its header declares {tuple(shape)} {dtype} "
                          f"= {expected} bytes of data, the file holds {actual}")
    if expected > SPARSE_SLACK:
        stored = data_bytes(path, offset, offset + expected)
        if stored is not None and expected - stored > SPARSE_SLACK and 2 * stored < expected:
            raise SourceError(f"{what}: {path} is a sparse file: its header declares {tuple(shape)} {dtype} "
                              f"= {expected} bytes of data, the file stores only {stored} (the rest are holes); "
                              "refusing it before any work")
    return tuple(int(d) for d in shape), dtype, bool(fortran)


def data_bytes(path: Path, start: int, stop: int, max_extents: int = 100_000) -> int | None:
    """Bytes of ``path`` between ``start`` and ``stop`` stored as data, not holes.

    Walks the file's data extents with ``SEEK_DATA``/``SEEK_HOLE`` (no data is read).

    Returns:
        The stored bytes, or None where the system or file system cannot tell (then
        the file counts as dense) or the file has more than ``max_extents`` extents.
    """
    import os

    seek_data, seek_hole = getattr(os, "SEEK_DATA", None), getattr(os, "SEEK_HOLE", None)
    if seek_data is None or seek_hole is None:
        return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        stored, pos = 0, start
        for _ in range(max_extents):
            if pos >= stop:
                return stored
            try:
                begin = os.lseek(fd, pos, seek_data)
            except OSError:  # ENXIO: no data after pos
                return stored
            if begin >= stop:
                return stored
            end = min(os.lseek(fd, begin, seek_hole), stop)
            stored += end - begin
            pos = end
        return None
    except OSError:
        return None
    finally:
        os.close(fd)


def load_npy(path: Path, what: str, **kwargs: Any) -> np.ndarray:
    """``np.load(path, allow_pickle=False, **kwargs)`` after :func:`check_npy`.

    Raises:
        SourceError: see :func:`check_npy`.
    """
    check_npy(path, what)
    try:
        return np.load(path, allow_pickle=False, **kwargs)
    except (ValueError, OSError, EOFError) as exc:
        raise SourceError(f"{what}: {path} is not a readable .npy file ({exc})") from None


def available_memory() -> int | None:
    """Memory available to new allocations in bytes (``MemAvailable`` of ``/proc/meminfo``), or None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    import os

    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_frames_fit_memory(n_frames: int, path: Path, what: str, available: int | None = None) -> None:
    """Refuse a capture whose per-frame results alone cannot fit in memory, before any work.

    Args:
        n_frames: binary frames the run will estimate a homography for.
        path: the capture (for the message).
        what: how the message names the reader, e.g. ``"source (npy-cube)"``.
        available: available memory in bytes (None: :func:`available_memory`; unknown: no check).

    Raises:
        SourceError: ``n_frames * BYTES_PER_FRAME`` exceeds the available memory; one
            line naming ``path``, the frames and both sizes (use ``start``/``stop``).
    """
    available = available_memory() if available is None else available
    needed = int(n_frames) * BYTES_PER_FRAME
    if available is not None and needed > available:
        raise SourceError(f"{what}: {path} declares {n_frames} frames; a run keeps at least {BYTES_PER_FRAME} "
                          f"bytes per frame ({needed / 2**30:.1f} GiB), more than the {available / 2**30:.1f} GiB "
                          "of memory available; select fewer frames (start, stop)")
