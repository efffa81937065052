"""Streaming reads across files and chunks give exactly the in-memory sums."""

import numpy as np
import pytest
from photonpano.photons import sum_packed_ranges, sum_unpacked_ranges
from photonpano.streaming import FrameFiles, FrameSegment


@pytest.fixture
def split_cube(tmp_path):
    """100 packed frames of 8x16 spread over three files with headers of different sizes."""
    frames = (np.random.default_rng(0).random((100, 8, 16)) < 0.4).astype(np.uint8)
    packed = np.packbits(frames, axis=-1)
    segments, start = [], 0
    for i, (n, header) in enumerate([(37, 0), (50, 11), (13, 128)]):
        path = tmp_path / f"part{i}.bin"
        path.write_bytes(b"h" * header + packed[start:start + n].tobytes())
        segments.append(FrameSegment(path, header, n))
        start += n
    return frames, packed, segments


@pytest.mark.parametrize("chunk_bytes", [16, 16 * 7, 2**20])
def test_sums_across_files_and_chunks_equal_the_in_memory_sums(split_cube, chunk_bytes):
    frames, packed, segments = split_cube
    files = FrameFiles(segments, (8, 2), np.uint8, chunk_bytes=chunk_bytes)
    assert files.n_frames == 100 and files.chunk_frames == max(1, chunk_bytes // 16)
    np.testing.assert_array_equal(files.read(30, 90), packed[30:90])
    for edges in ([0, 100], [5, 36, 37, 38, 87, 99], [36, 88]):
        edges = np.array(edges)
        want = sum_unpacked_ranges(frames, edges)
        np.testing.assert_array_equal(files.sum_ranges(edges, sum_packed_ranges, (8, 16)), want)


def test_bad_ranges_and_short_files_raise(split_cube):
    frames, packed, segments = split_cube
    files = FrameFiles(segments, (8, 2))
    with pytest.raises(ValueError, match="strictly increasing"):
        files.sum_ranges(np.array([5, 5]), sum_packed_ranges, (8, 16))
    with pytest.raises(ValueError, match="leave the capture of 100 frames"):
        files.sum_ranges(np.array([0, 101]), sum_packed_ranges, (8, 16))
    segments[2].path.write_bytes(b"x" * 200)  # the file shrank under us
    with pytest.raises(OSError, match="short read"):
        files.read(90, 100)
