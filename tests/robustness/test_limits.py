"""Limits before work: sparse .npy captures and zarr cubes chunked to hang or exhaust memory are refused at once."""

from __future__ import annotations

import time

import numpy as np
import pytest
from photonpano.errors import SourceError
from photonpano.npy_header import data_bytes
from robust import assert_one_line_error, invoke, run_subprocess

DECLARED = (10**8, 64, 16)
"""10^8 bit-packed 64x128 frames: 102.4 GB declared."""


def _sparse_npy(path, shape=DECLARED, dense_bytes: int = 0):
    """An .npy file of the declared length whose data is a hole (except ``dense_bytes`` written at the start)."""
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "|u1", "fortran_order": False, "shape": shape})
        offset = handle.tell()
        handle.write(np.random.default_rng(0).integers(0, 256, dense_bytes, np.uint8).tobytes())
        handle.truncate(offset + int(np.prod(shape)))
    return path


def _fingerprint(path):
    """Size, mtime and sha256 of the first MiB and of the stored data extents (a sparse file is not read whole)."""
    import hashlib

    info = path.stat()
    with open(path, "rb") as handle:
        head = hashlib.sha256(handle.read(2**20)).hexdigest()
    return info.st_size, info.st_mtime_ns, head, data_bytes(path, 0, info.st_size)


@pytest.fixture
def sparse(tmp_path):
    path = _sparse_npy(tmp_path / "sparse.npy")
    stored = data_bytes(path, 0, path.stat().st_size)
    if stored is None or stored > 2**20:
        pytest.skip("this file system does not report holes (SEEK_HOLE)")
    return path


@pytest.mark.parametrize("command", ["pano", "convert"])
def test_a_sparse_npy_declaring_1e8_frames_is_refused_before_any_work(tmp_path, sparse, command):
    out = tmp_path / ("out" if command == "pano" else "cube.zarr")
    before = _fingerprint(sparse)
    start = time.perf_counter()
    result = run_subprocess(command, sparse, "-o", out, timeout=60)
    line = assert_one_line_error(result, sparse, "sparse file", str(DECLARED), str(int(np.prod(DECLARED))),
                                 "stores only")
    assert time.perf_counter() - start < 30, line
    assert not out.exists() and _fingerprint(sparse) == before


def test_a_dense_cube_with_a_short_hole_is_accepted(tmp_path):
    """Holes up to 64 MiB (a file system that stores zero blocks as holes) are not a sparse capture."""
    from photonpano.npy_header import check_npy

    path = _sparse_npy(tmp_path / "ok.npy", shape=(2000, 64, 16), dense_bytes=1000 * 64 * 16)
    assert check_npy(path, "test")[0] == (2000, 64, 16)


@pytest.mark.parametrize("shape, chunks, message", [
    ((96_000, 32, 8), (1, 32, 8), "96000 chunks of only 256 bytes"),
    ((200_000, 256, 64), (1, 256, 64), "200000 chunks of (1, 256, 64), over the limit of 100000"),
    ((200_000, 1024, 1024), (3000, 1024, 1024), "3145728000 bytes decompressed, over the limit"),
    ((200_000, 256, 64), (256, 256, 64), None),  # photonpano convert's chunking
    ((20_000_000, 256, 64), (256, 256, 64), None),  # 78 125 chunks of 4 MiB: a long capture
])
def test_zarr_chunking_limits(tmp_path, shape, chunks, message):
    from photonpano.plugins.sources.zarr_cube import check_zarr_layout

    path = tmp_path / "cube.zarr"
    if message is None:
        check_zarr_layout(path, "source (zarr-cube)", shape, chunks, np.uint8)
        return
    with pytest.raises(SourceError) as info:
        check_zarr_layout(path, "source (zarr-cube)", shape, chunks, np.uint8)
    text = str(info.value)
    assert message in text and str(path) in text and "\n" not in text


def test_a_zarr_cube_of_tiny_chunks_is_refused_in_one_line(tmp_path):
    zarr = pytest.importorskip("zarr")
    path = tmp_path / "tiny.zarr"
    array = zarr.create_array(str(path), shape=(12_000, 8, 2), dtype=np.uint8, chunks=(1, 8, 2))
    array[:] = np.random.default_rng(0).integers(0, 256, (12_000, 8, 2), np.uint8)
    start = time.perf_counter()
    result = run_subprocess("pano", path, "-o", tmp_path / "out", timeout=60)
    assert_one_line_error(result, path, "12000 chunks of only 16 bytes")
    assert time.perf_counter() - start < 30 and not (tmp_path / "out").exists()


def test_more_frames_than_memory_can_hold_results_for_is_refused(tmp_path, small_cube, monkeypatch):
    """Declared frames x the bytes a run keeps per frame vs the memory available (patched small here)."""
    from photonpano import npy_header

    monkeypatch.setattr(npy_header, "available_memory", lambda: 400 * npy_header.BYTES_PER_FRAME - 1)
    out = tmp_path / "out"
    line = assert_one_line_error(invoke("pano", small_cube, "-o", out), small_cube, "declares 400 frames",
                                 "memory available", "start, stop")
    assert "GiB" in line and not out.exists()
    monkeypatch.setattr(npy_header, "available_memory", lambda: 400 * npy_header.BYTES_PER_FRAME)
    npy_header.check_frames_fit_memory(400, small_cube, "test")  # exactly enough: accepted
