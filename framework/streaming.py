"""Streaming reads of frame stacks stored in files, a bounded chunk at a time.

Captures can be far larger than memory (a 200 000-frame SwissSPAD cube is 1.6 GB, a
raw readout folder holds hundreds of 8 MiB files). Sources built on :class:`FrameFiles`
read the frames they need with ordinary file reads into a buffer of at most
``chunk_bytes`` and never memory-map a whole capture, so the resident memory of a run
does not grow with the capture length (a memory map would keep every page it touched
resident, and counted in the process's RSS, for as long as the page cache holds it).

Frames are addressed by a global index across all files, in file order.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
from numpy.typing import NDArray

from .outputs.partial import claim_partial, release_partial

__all__ = ["FrameSegment", "FrameFiles", "DEFAULT_CHUNK_BYTES", "sum_ranges_by_blocks", "ReopenOnPickle",
           "write_npy_blocks", "claim_partial"]

DEFAULT_CHUNK_BYTES = 32 * 2**20
"""Default read buffer size of :class:`FrameFiles` in bytes (32 MiB)."""


class ReopenOnPickle:
    """Mixin of sources backed by files: a pickle says "reopen this file with these settings".

    A source that streams a capture from files (an ``.npy`` memory map, a zarr array,
    SwissSPAD readouts, a video or ``.mraw``) pickles as its class and validated config only, a few hundred
    bytes, never as the photons it could read; unpickling opens the files again (and
    repeats the checks of ``__init__``). This is what lets a task that holds the source
    run in another process or on a cluster worker that sees the same files (shared
    storage). Sources that hold their frames in memory (``simulate``) pickle whole.

    The class must rebuild itself completely from ``self.config`` (its ``__init__``
    takes the config as its only argument).
    """

    config: Any

    def __reduce__(self) -> tuple[type, tuple[Any]]:
        return type(self), (self.config,)


def write_npy_blocks(output: Path, shape: tuple[int, ...], dtype: Any, blocks: Iterable[NDArray],
                     progress: Callable[[int, int], None] | None = None, restart: bool = False) -> None:
    """Write an ``.npy`` file from consecutive blocks along its first axis, streaming.

    The file is written under ``<output>.part`` and renamed when complete, so an
    interrupted write leaves no truncated ``output`` behind. The ``.part`` file is
    created exclusively (never through a symbolic link, never over an existing path:
    one left by an interrupted conversion is removed only with ``restart``, see
    :func:`photonpano.outputs.partial.claim_partial`), and only a ``.part`` this call
    created is deleted.

    Args:
        output: the ``.npy`` file to write (replaced if it exists: callers check first).
        shape: the full array shape, e.g. ``(T, H, W/8)`` for a bit-packed photon cube.
        dtype: the element dtype (a C-ordered array of it is written).
        blocks: arrays of shape ``(t_i, *shape[1:])`` whose ``t_i`` sum to ``shape[0]``.
        progress: called as ``progress(rows_done, shape[0])`` after each block.
        restart: remove the ``.part`` left by an interrupted conversion first and
            start again (``photonpano convert --resume``).

    Raises:
        ValueError: if the blocks do not add up to ``shape``.
        OutputError: ``output`` is a symbolic link, ``<output>.part`` exists (of any
            kind, a link included), or an OS error (full disk, read-only folder) while
            writing; one line naming the path (and, for a full disk, the space needed).
    """
    from .outputs.files import oserror, refuse_symlink

    dtype = np.dtype(dtype)
    refuse_symlink(output, "output")
    partial = claim_partial(output, restart)
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    done = 0
    read_errors: list[OSError] = []

    def reads() -> Iterable[NDArray]:
        try:
            yield from blocks
        except OSError as exc:  # an input failed: the caller names it
            read_errors.append(exc)
            raise

    try:
        fd = os.open(partial, os.O_WRONLY | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0))
        with os.fdopen(fd, "wb") as f:
            np.lib.format.write_array_header_2_0(f, {"descr": np.lib.format.dtype_to_descr(dtype),
                                                     "fortran_order": False, "shape": tuple(shape)})
            for block in reads():
                if block.shape[1:] != tuple(shape[1:]) or done + len(block) > shape[0]:
                    raise ValueError(f"{output}: block of shape {block.shape} does not fit an array of shape {shape}")
                f.write(np.ascontiguousarray(block, dtype=dtype).tobytes())
                done += len(block)
                if progress is not None:
                    progress(done, shape[0])
        if done != shape[0]:
            raise ValueError(f"{output}: blocks hold {done} of the {shape[0]} rows of shape {shape}")
        partial.replace(output)
    except OSError as exc:
        if read_errors and exc is read_errors[0]:
            raise
        raise oserror(output, exc, needed=nbytes) from None
    finally:
        partial.unlink(missing_ok=True)
        release_partial(output)


@dataclass(frozen=True)
class FrameSegment:
    """A run of equally shaped frames stored contiguously in one file.

    Attributes:
        path: the file.
        offset: byte offset of the first frame in the file.
        n_frames: number of whole frames stored.
    """

    path: Path
    offset: int
    n_frames: int


class FrameFiles:
    """Frames of one shape and dtype spread over consecutive file segments.

    Args:
        segments: the file segments, in frame order.
        frame_shape: shape of one stored frame, e.g. ``(256, 64)`` for a bit-packed
            256x512 binary frame.
        dtype: stored element dtype (uint8 for bit-packed frames).
        chunk_bytes: largest read buffer in bytes (at least one frame is read).

    Attributes:
        n_frames: total number of frames T.
        frame_bytes: bytes per stored frame.
        starts: (S + 1,) int64 global index of the first frame of each segment, then T.
    """

    def __init__(self, segments: list[FrameSegment], frame_shape: tuple[int, ...], dtype=np.uint8,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES) -> None:
        self.segments = list(segments)
        self.frame_shape = tuple(int(s) for s in frame_shape)
        self.dtype = np.dtype(dtype)
        self.frame_bytes = int(np.prod(self.frame_shape)) * self.dtype.itemsize
        self.chunk_frames = max(1, int(chunk_bytes) // max(self.frame_bytes, 1))
        self.starts = np.concatenate([[0], np.cumsum([s.n_frames for s in self.segments])]).astype(np.int64)
        self.n_frames = int(self.starts[-1])

    def read(self, start: int, stop: int, out: NDArray | None = None) -> NDArray:
        """Read frames ``start:stop`` (global indices) into a new array, or into ``out``.

        Args:
            start: first frame.
            stop: one past the last frame (``start <= stop <= n_frames``).
            out: a C-contiguous buffer of the stored dtype holding at least
                ``stop - start`` frames; its first ``stop - start`` frames are filled and
                returned (None: a new array).

        Returns:
            (stop - start, *frame_shape) array of the stored dtype.

        Raises:
            ValueError: if the range leaves the frames.
            OSError: if a file cannot be read or is shorter than its segment says.
        """
        if not 0 <= start <= stop <= self.n_frames:
            raise ValueError(f"frames {start}:{stop} leave the {self.n_frames} stored frames")
        if out is None:
            out = np.empty((stop - start,) + self.frame_shape, dtype=self.dtype)
        else:
            out = out[:stop - start]
        flat = out.reshape(-1).view(np.uint8)
        pos, written = start, 0
        while pos < stop:
            s = int(np.searchsorted(self.starts, pos, side="right")) - 1
            seg = self.segments[s]
            end = min(stop, int(self.starts[s + 1]))
            nbytes = (end - pos) * self.frame_bytes
            with open(seg.path, "rb") as f:
                f.seek(seg.offset + (pos - int(self.starts[s])) * self.frame_bytes)
                got = f.readinto(memoryview(flat[written:written + nbytes]))
            if got != nbytes:
                raise OSError(f"{seg.path}: short read ({got} of {nbytes} bytes); the file changed or is truncated")
            written += nbytes
            pos = end
        return out

    def blocks(self, start: int, stop: int):
        """Yield ``(block_start, frames)`` for consecutive chunks covering ``start:stop``.

        Chunks hold at most ``chunk_frames`` frames and never straddle a segment (file).
        Every chunk is read into the same buffer: a chunk is valid until the next one
        is yielded (copy it to keep it). A fresh buffer per chunk costs a page fault per
        4 KiB (buffers this large are mapped anew by the allocator): 0.6 s instead of
        0.25 s per pass over a 1.6 GB capture.

        Args:
            start: first frame.
            stop: one past the last frame.
        """
        buffer = np.empty((min(self.chunk_frames, max(stop - start, 0)),) + self.frame_shape, dtype=self.dtype)
        pos = start
        while pos < stop:
            s = int(np.searchsorted(self.starts, pos, side="right")) - 1
            end = min(stop, pos + self.chunk_frames, int(self.starts[s + 1]))
            yield pos, self.read(pos, end, out=buffer)
            pos = end

    def sum_ranges(self, edges: NDArray[np.int64], count: Callable[[NDArray, NDArray[np.int64]], NDArray],
                   out_shape: tuple[int, ...], out_dtype=np.uint16) -> NDArray:
        """Sum frames over consecutive ranges, reading one bounded chunk at a time.

        :func:`sum_ranges_by_blocks` over this file's frames and chunks: ``edges``,
        ``count`` (e.g. :func:`photonpano.photons.sum_packed_ranges`), ``out_shape`` and
        ``out_dtype`` as there; (B, *out_shape) sums; ValueError for edges that are not
        increasing or leave the frames.
        """
        return sum_ranges_by_blocks(edges, self.n_frames, self.blocks, count, out_shape, out_dtype)


def sum_ranges_by_blocks(edges: NDArray[np.int64], n_frames: int,
                         blocks: Callable[[int, int], Iterable[tuple[int, NDArray]]],
                         count: Callable[[NDArray, NDArray[np.int64]], NDArray],
                         out_shape: tuple[int, ...], out_dtype=np.uint16) -> NDArray:
    """Sum frames over consecutive ranges from blocks of frames read one at a time.

    The streaming loop shared by the sources: each block is split at the range edges
    inside it, ``count`` sums the pieces, and each piece is added to its range.

    Args:
        edges: (B + 1,) strictly increasing frame indices within ``[0, n_frames]``.
        n_frames: number of frames of the capture.
        blocks: ``blocks(start, stop)`` yields ``(block_start, frames)`` for consecutive
            in-memory blocks covering frames ``start:stop``.
        count: ``count(block, local_edges) -> (b, *out_shape)`` sums a block over the
            ranges ``local_edges`` (relative to the block's first frame). A count
            function with the attribute ``adds_into_out = True`` (e.g.
            :func:`photonpano.photons.sum_packed_ranges`) is called with ``out=`` the
            rows of its ranges instead, and adds into them: no second pass.
        out_shape: shape of one range's sum, e.g. ``(H, W)``.
        out_dtype: dtype of the sums.

    Returns:
        (B, *out_shape) sums; range ``b`` covers frames ``edges[b]:edges[b+1]``.

    Raises:
        ValueError: if the edges are not increasing or leave the frames.
    """
    from .photons import check_frame_edges

    edges = check_frame_edges(edges, n_frames)
    out = np.zeros((max(len(edges) - 1, 0),) + tuple(out_shape), dtype=out_dtype)
    if len(edges) < 2:
        return out
    adds = getattr(count, "adds_into_out", False)
    for pos, block in blocks(int(edges[0]), int(edges[-1])):
        end = pos + len(block)
        inner = edges[(edges > pos) & (edges < end)]
        local = np.concatenate([[pos], inner, [end]]).astype(np.int64)
        # each piece is the part of one range that lies in this block: consecutive ranges
        first = int(np.searchsorted(edges, pos, side="right")) - 1
        if adds:
            count(block, local - pos, out=out[first:first + len(local) - 1])
        else:
            out[first:first + len(local) - 1] += count(block, local - pos)
    return out
