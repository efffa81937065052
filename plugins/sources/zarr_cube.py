"""Source ``zarr-cube``: a photon cube stored as a zarr array (chunked, compressed).

Zarr (https://zarr.dev) stores an array as separately compressed chunks in a folder
(or an object store), so a capture on shared or cloud storage can be read a few
chunks at a time by any number of workers. The array has the layout of ``npy-cube``:
``(T, H, W/8)`` uint8 bit-packed along the width, most significant bit first, or
``(T, H, W)`` bool/uint8 0/1 unpacked, chunked along time (``photonpano convert``
writes whole frames per chunk). Every ``npy-cube`` setting applies (frame range,
frame rate, exposure, layout detection, the SwissSPAD sensor corrections).

Frames are read in blocks of whole zarr chunks of at most ``chunk_mb`` (at least one
chunk), so memory does not grow with the capture. ``photonpano convert`` turns an
``.npy`` cube into a zarr cube and back (:func:`convert_npy_to_zarr`,
:func:`convert_zarr_to_npy`). Needs the ``dask`` extra (``pip install
'photonpano[dask]'``, which installs ``zarr``); zarr is imported when a cube is opened.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.stages import SourceConfig
from photonpano.streaming import sum_ranges_by_blocks

from .npy_cube import NpyCube, NpyCubeConfig

__all__ = ["ZarrCubeConfig", "ZarrCube", "ZarrFrames", "convert_npy_to_zarr", "convert_zarr_to_npy",
           "CHUNK_BYTES", "MAX_CHUNKS", "MAX_CHUNK_BYTES", "check_zarr_layout"]

CHUNK_BYTES = 4 * 2**20
"""Uncompressed size of the time chunks :func:`convert_npy_to_zarr` writes (about 4 MiB:
256 bit-packed 256x512 frames)."""

MAX_CHUNKS = 100_000
"""Most chunks (inner chunks where the array is sharded) a zarr cube may have."""
MAX_SMALL_CHUNKS = 10_000
"""Most chunks a zarr cube may have when they are smaller than :data:`SMALL_CHUNK_BYTES`."""
SMALL_CHUNK_BYTES = 64 * 2**10
"""Chunks smaller than this (64 KiB uncompressed) cost more in per-chunk overhead than in data."""
MAX_CHUNK_BYTES = 512 * 2**20
"""Largest decompressed chunk a zarr cube may have (512 MiB); each read decompresses whole chunks."""


class ZarrCubeConfig(NpyCubeConfig):
    """A photon cube stored as a zarr array, bit-packed or unpacked, read chunk by chunk."""

    plugin: Literal["zarr-cube"] = "zarr-cube"
    path: Path
    """The zarr array: a folder such as ``capture.zarr`` (zarr format 2 or 3, read with zarr >= 3)."""

    requires: ClassVar[tuple[str, ...]] = ("zarr",)
    install_hint: ClassVar[str] = "pip install 'photonpano[dask]'"

    def build(self) -> ZarrCube:
        """Open the zarr array (read-only)."""
        return ZarrCube(self)


class ZarrFrames:
    """Frames ``start:start + n_frames`` of a zarr array, read in blocks of whole chunks.

    Args:
        array: a ``(T, ...)`` zarr array chunked along its first axis.
        start: the first frame of the selection.
        n_frames: frames selected.
        chunk_bytes: largest block in bytes (uncompressed); at least one chunk is read.

    Attributes:
        chunk_frames: frames per block (a multiple of the array's time chunk).
    """

    def __init__(self, array: Any, start: int, n_frames: int, chunk_bytes: int) -> None:
        self.array, self.start, self.n_frames = array, int(start), int(n_frames)
        self.time_chunk = int(array.chunks[0])
        frame_bytes = int(np.prod(array.shape[1:])) * array.dtype.itemsize
        self.chunk_frames = max(1, int(chunk_bytes) // max(frame_bytes * self.time_chunk, 1)) * self.time_chunk

    def blocks(self, start: int, stop: int) -> Iterator[tuple[int, NDArray]]:
        """Yield ``(block_start, frames)`` covering selected frames ``start:stop``, chunk-aligned."""
        pos = start
        while pos < stop:
            first = self.start + pos
            end = min(stop, pos + self.chunk_frames - first % self.time_chunk)
            yield pos, np.asarray(self.array[first:self.start + end])
            pos = end

    def sum_ranges(self, edges: NDArray[np.int64], count: Callable[[NDArray, NDArray[np.int64]], NDArray],
                   out_shape: tuple[int, ...], out_dtype: Any = np.uint16) -> NDArray:
        """Sum frames over ranges, a block at a time (see :meth:`photonpano.streaming.FrameFiles.sum_ranges`)."""
        return sum_ranges_by_blocks(edges, self.n_frames, self.blocks, count, out_shape, out_dtype)


class ZarrCube(NpyCube):
    """A zarr photon cube (see :class:`ZarrCubeConfig`); everything but the reads is ``npy-cube``'s.

    Pickles as its config, never as the photons (the array is opened again where it
    is unpickled; see :class:`~photonpano.streaming.ReopenOnPickle`).
    """

    label = "zarr-cube"

    def __init__(self, config: ZarrCubeConfig) -> None:
        """Open and check the array.

        Raises:
            SourceError: a missing path, a folder that is not a zarr array, or any check
                of ``npy-cube`` (dtype, dimensions, frame range); messages name the path.
        """
        self._open(config, open_zarr(config.path, "source (zarr-cube)"))
        self.frames = ZarrFrames(self.cube, config.start, self.n_frames, int(config.chunk_mb * 2**20))


def open_zarr(path: Path, what: str) -> Any:
    """Open the zarr array at ``path`` read-only.

    Args:
        path: the array's folder (or any store path zarr understands).
        what: how messages name it, e.g. ``"source (zarr-cube)"``.

    Raises:
        SourceError: zarr is not installed, ``path`` does not exist, it holds no
            zarr array (a group, another folder), or its chunking is out of bounds
            (:func:`check_zarr_layout`); one line naming ``path``.
    """
    try:
        import zarr
    except ImportError as exc:
        raise SourceError(f"{what}: reading {path} needs zarr: pip install 'photonpano[dask]'") from exc
    if not Path(path).exists():
        raise SourceError(f"{what}: {path} does not exist")
    try:
        array = zarr.open_array(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for "not an array here"
        raise SourceError(f"{what}: {path} is not a zarr array ({type(exc).__name__}: {exc})") from exc
    check_zarr_layout(path, what, array.shape, array.chunks, array.dtype)
    return array


def check_zarr_layout(path: Path, what: str, shape: tuple[int, ...], chunks: tuple[int, ...], dtype: Any) -> None:
    """Refuse a zarr array whose chunking would make reading it hang or exhaust memory, before any read.

    Args:
        path: the array (for the message).
        what: how the message names the reader, e.g. ``"source (zarr-cube)"``.
        shape: the array shape, e.g. ``(T, H, W/8)``.
        chunks: the chunk shape (the inner chunks of a sharded array): the unit that
            is decompressed, and whose count sets the per-chunk overhead of a read.
        dtype: the element dtype.

    Raises:
        SourceError: more than :data:`MAX_CHUNKS` chunks, more than
            :data:`MAX_SMALL_CHUNKS` chunks under :data:`SMALL_CHUNK_BYTES`, or a chunk
            over :data:`MAX_CHUNK_BYTES` decompressed; one line naming ``path``, the
            count or size and the limit.
    """
    import math

    chunks = tuple(max(int(c), 1) for c in chunks)
    itemsize = np.dtype(dtype).itemsize
    chunk_bytes = math.prod(chunks) * itemsize
    count = math.prod(-(-int(n) // c) for n, c in zip(shape, chunks))
    advice = "rechunk it along time (whole frames, a few MiB per chunk)"
    if chunk_bytes > MAX_CHUNK_BYTES:
        raise SourceError(f"{what}: {path} has chunks of {chunks} {np.dtype(dtype)} = {chunk_bytes} bytes "
                          f"decompressed, over the limit of {MAX_CHUNK_BYTES} (512 MiB); {advice}")
    if count > MAX_CHUNKS:
        raise SourceError(f"{what}: {path} has {count} chunks of {chunks}, over the limit of {MAX_CHUNKS}; "
                          f"{advice}")
    if count > MAX_SMALL_CHUNKS and chunk_bytes < SMALL_CHUNK_BYTES:
        raise SourceError(f"{what}: {path} has {count} chunks of only {chunk_bytes} bytes each (over "
                          f"{MAX_SMALL_CHUNKS} chunks under {SMALL_CHUNK_BYTES} bytes); {advice}")


def convert_npy_to_zarr(source: Path, output: Path, *, chunk_bytes: int = CHUNK_BYTES,
                        progress: Callable[[int, int], None] | None = None, restart: bool = False) -> int:
    """Copy an ``.npy`` photon cube into a new zarr array, streaming.

    The array keeps the cube's shape and dtype (a bit-packed cube stays bit-packed),
    chunked along time in whole frames of about ``chunk_bytes`` and compressed with
    Zstandard at level 1 (smaller and faster to read and write than zarr's default
    level 3 on photon cubes; see docs/capture_formats.md). It is written under ``<output>.part`` and renamed when
    complete. Memory use is one chunk.

    Args:
        source: a ``.npy`` photon cube, ``(T, H, W/8)`` or ``(T, H, W)``, C order.
        output: the zarr folder to create (must not exist).
        chunk_bytes: uncompressed bytes per chunk (at least one frame).
        progress: called as ``progress(frames_done, total_frames)``.
        restart: remove the ``.part`` left by an interrupted conversion first (see
            :func:`photonpano.outputs.partial.claim_partial`).

    Returns:
        The number of frames written.

    Raises:
        SourceError: a missing, unreadable or non-cube ``source`` (see ``npy-cube``), an
            existing ``output``, or zarr not installed.
        OutputError: ``output`` is a symbolic link, ``<output>.part`` exists (not this
            conversion's: it is never written through nor removed), or an OS error while
            writing (full disk); one line naming the path.
    """
    from photonpano.npy_header import load_npy
    from photonpano.outputs.files import oserror, refuse_symlink
    from photonpano.outputs.partial import claim_partial, release_partial

    refuse_symlink(output, "output")
    if output.exists():
        raise SourceError(f"convert: {output} exists; refusing to overwrite it")
    if not source.is_file():
        raise SourceError(f"convert: {source} does not exist")
    cube = load_npy(source, f"convert ({source.name})", mmap_mode="r")
    if cube.ndim != 3 or np.isfortran(cube):
        raise SourceError(f"convert: {source} has shape {cube.shape}; expected a C-ordered photon cube (T, H, W/8) "
                          "or (T, H, W)")
    try:
        import zarr
        from zarr.codecs import ZstdCodec
    except ImportError:
        raise SourceError(f"convert: writing {output} needs zarr: pip install 'photonpano[dask]'") from None
    partial = claim_partial(output, restart)  # refuses a .part that is not ours (a link, a folder, a file)
    partial.unlink()

    frame_bytes = int(np.prod(cube.shape[1:])) * cube.dtype.itemsize
    step = max(1, int(chunk_bytes) // max(frame_bytes, 1))
    try:
        partial.mkdir()
    except OSError as exc:
        release_partial(output)
        raise oserror(partial, exc) from None
    try:
        array = zarr.create_array(str(partial), shape=cube.shape, dtype=cube.dtype, chunks=(step, *cube.shape[1:]),
                                  compressors=[ZstdCodec(level=1)], overwrite=True)
        for start in range(0, len(cube), step):
            stop = min(start + step, len(cube))
            array[start:stop] = np.asarray(cube[start:stop])
            if progress is not None:
                progress(stop, len(cube))
        partial.rename(output)
    except OSError as exc:
        raise oserror(output, exc, needed=int(cube.nbytes)) from None
    finally:
        _remove_tree(partial)
        release_partial(output)
    return len(cube)


def convert_zarr_to_npy(source: Path, output: Path, *, chunk_bytes: int = 32 * 2**20,
                        progress: Callable[[int, int], None] | None = None, restart: bool = False) -> int:
    """Copy a zarr photon cube into a new ``.npy`` file, streaming (the inverse of :func:`convert_npy_to_zarr`).

    Args:
        source: the zarr array, ``(T, H, W/8)`` or ``(T, H, W)``.
        output: the ``.npy`` file to write (must not exist).
        chunk_bytes: largest read block in bytes (whole zarr chunks, at least one).
        progress: called as ``progress(frames_done, total_frames)``.
        restart: remove the ``.part`` left by an interrupted conversion first.

    Returns:
        The number of frames written.

    Raises:
        SourceError: a missing or non-array ``source``, an array that is not 3-d, an
            existing ``output``, or zarr not installed.
    """
    from photonpano.outputs.files import refuse_symlink
    from photonpano.streaming import write_npy_blocks

    refuse_symlink(output, "output")
    if output.exists():
        raise SourceError(f"convert: {output} exists; refusing to overwrite it")
    array = open_zarr(source, "convert")
    if array.ndim != 3:
        raise SourceError(f"convert: {source} has shape {array.shape}; expected a photon cube (T, H, W/8) or (T, H, W)")
    frames = ZarrFrames(array, 0, array.shape[0], chunk_bytes)
    write_npy_blocks(output, array.shape, array.dtype, (block for _, block in frames.blocks(0, frames.n_frames)),
                     progress, restart)
    return frames.n_frames


def _remove_tree(path: Path) -> None:
    """Delete a partly written zarr folder this conversion created, if any (never a link's target)."""
    import shutil

    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``zarr-cube`` source."""
    return [ZarrCubeConfig]


@hookimpl
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Read ``*.zarr`` inputs of ``photonpano pano`` with this source."""
    if path.suffix.lower() == ".zarr":
        return {"plugin": "zarr-cube", "path": str(path)}
    return None
