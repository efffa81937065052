"""Registration at a binned resolution: the capture seen through k x k pixel binning.

Motion is estimated on merged frames, and the locators register them at a fraction of
the sensor resolution anyway (SIFT detects on half-resolution frames, ECC against the
panorama stops at its half-resolution pyramid level). Merging them at that resolution
in the first place, by summing the photons of k x k sensor pixels (*binning*, as a
camera's readout does), gives the locators the same images for a k^2-th of the
warping, flux and tone-mapping work.

:class:`RegistrationGrid` is the change of coordinates between the sensor's pixels and
the binned ones; :class:`~photonpano.schemes.binned.Binned` hands its scheme the binned
capture and binned homographies and turns their keyframes back into sensor pixels, so
the level loop, schemes, mergers and locators need not know about binning. The
panorama is composited from the full-resolution photons.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import geometry
from ..imaging import bin_counts
from ..jit import cached_njit
from ..records import LocateResult
from ..stages import LocatorConfig, PhotonSource

__all__ = ["BinnedSource", "BinnedBlocks", "RegistrationGrid", "block_size", "in_merged_pixels"]


def in_merged_pixels(config: LocatorConfig, binning: int) -> LocatorConfig:
    """A locator config with its lengths in sensor pixels turned into pixels of k x k binned merged frames.

    Convention for every locator (:class:`~photonpano.stages.LocatorConfig`): a field
    whose name ends in ``_px`` is a length in sensor pixels (an inlier threshold, a
    largest correction, a border). Float lengths are divided by ``binning``, integer
    ones rounded up; the framework builds locators from this copy.

    Args:
        config: the spec's locator config.
        binning: sensor pixels per merged-frame pixel along each axis (>= 1).

    Returns:
        ``config`` itself when ``binning`` is 1, else an updated copy.
    """
    if binning == 1:
        return config
    update = {}
    for name, value in config:
        if name.endswith("_px") and isinstance(value, (int, float)) and not isinstance(value, bool):
            update[name] = -(-value // binning) if isinstance(value, int) else value / binning
    return config.model_copy(update=update)


@cached_njit(nogil=True)
def _sum_block_ranges(stored, starts, scale, out):  # pragma: no cover - compiled
    for r in range(len(starts) - 1):
        total = out[r]
        first = stored[starts[r]]
        for i in range(first.size):
            total[i] = first[i]
        for b in range(starts[r] + 1, starts[r + 1]):
            block = stored[b]
            for i in range(block.size):
                total[i] += block[i]
        for i in range(total.size):
            total[i] *= scale


class BinnedBlocks:
    """Binned photon counts of consecutive blocks of frames, counted once and kept on disk.

    Every level merges (and each mosaic template composites) the same photons
    again. Binned k x k and summed over blocks of ``block`` frames into one byte per
    binned pixel, a bit-packed capture shrinks ``block k^2 / 8`` times (254x496 frames,
    k = 2, blocks of 25: 126 MB per 100 000 frames against 1.57 GB): counted once, in
    parallel, into an anonymous temporary file, any range of whole blocks is then read
    back and added in a fraction of a counting pass. Reads go through ordinary file reads (the page
    cache), not a memory map, so the process's resident memory does not grow with the
    capture.

    Args:
        source: the capture (binary frames).
        factor: binning k (>= 1).
        block: frames per block (``block x k^2 <= 65535``).
        executor: counts chunks of blocks in parallel (threads of this process).
        chunk_blocks: blocks counted per task.

    Raises:
        OSError: if the temporary file cannot be written (e.g. the disk is full).
    """

    def __init__(self, source: PhotonSource, factor: int, block: int, executor: Any = None,
                 chunk_blocks: int = 64) -> None:
        """Count every whole block of ``source`` (see the class)."""
        import os
        import tempfile

        from ..executor import SerialExecutor

        self.factor, self.block = int(factor), int(block)
        self.n_blocks = source.n_frames // self.block
        self.height, self.width = source.height // self.factor, source.width // self.factor
        self.dtype = np.dtype(np.uint8 if self.block * self.factor ** 2 <= 255 else np.uint16)
        self._block_bytes = self.height * self.width * self.dtype.itemsize
        self._file = tempfile.TemporaryFile(prefix="photonpano-blocks-")
        fd = self._file.fileno()
        os.ftruncate(fd, self.n_blocks * self._block_bytes)

        def count(first: int) -> int:
            last = min(first + chunk_blocks, self.n_blocks)
            edges = np.arange(first, last + 1, dtype=np.int64) * self.block
            sums = bin_counts(source.sum_ranges(edges), self.factor, self.dtype, mean=False)
            os.pwrite(fd, sums.tobytes(), first * self._block_bytes)
            return last - first

        (executor or SerialExecutor()).map(count, list(range(0, self.n_blocks, chunk_blocks)))

    def covers(self, edges: NDArray[np.int64]) -> bool:
        """Whether every edge is a block boundary within the stored blocks."""
        return bool(len(edges) and np.all(edges % self.block == 0) and edges[-1] <= self.n_blocks * self.block)

    def mean_counts(self, edges: NDArray[np.int64]) -> NDArray[np.float32]:
        """(B, H // k, W // k) float32 mean detections per sensor pixel over ranges ``edges`` (see :meth:`covers`)."""
        import os

        blocks = np.asarray(edges, np.int64) // self.block
        first, last = int(blocks[0]), int(blocks[-1])
        raw = os.pread(self._file.fileno(), (last - first) * self._block_bytes, first * self._block_bytes)
        stored = np.frombuffer(raw, self.dtype).reshape(last - first, self.height * self.width)
        # sequential float32 sums of integer counts < 2^24: exact; 10-30x faster than np.add.reduceat's cast
        sums = np.empty((len(blocks) - 1, self.height, self.width), np.float32)
        _sum_block_ranges(stored, blocks - first, np.float32(1.0 / self.factor ** 2),
                          sums.reshape(len(blocks) - 1, -1))
        return sums

    def close(self) -> None:
        """Delete the temporary file."""
        self._file.close()


def block_size(boundaries: NDArray[np.int64], group_size: int, largest: int = 32) -> int:
    """Frames per block of :class:`BinnedBlocks` whose block grid holds every group boundary.

    The largest divisor of the boundaries' greatest common divisor that is at most
    ``min(largest, group_size // 16)``: a block then moves by at most a sixteenth of a
    group's motion blur (the group-size plan bounds that blur), and a level's groups
    and sub-batches are whole blocks.

    Args:
        boundaries: frame indices where groups start or stop, at every level, and the
            capture length.
        group_size: binary frames per group m.
        largest: most frames per block.

    Returns:
        Frames per block (1: no block size fits, count directly).
    """
    step = int(np.gcd.reduce(np.asarray(boundaries, np.int64)))
    limit = max(1, min(largest, group_size // 16))
    return max((d for d in range(1, limit + 1) if step % d == 0), default=1)


class BinnedSource(PhotonSource):
    """A capture seen through k x k pixel binning (a view: the photons stay where they are).

    :meth:`sum_ranges` returns, per binned pixel, the *mean* count of its k x k sensor
    pixels (float32), so ``sums / frames`` is still a detection probability per binary
    frame (and the flux MLE, paper Eq. 3, keeps its meaning); intensity captures give
    mean intensities. Binned pixel ``i`` covers sensor pixels ``k i .. k i + k - 1``;
    with pixel centres at integers, sensor ``x`` is binned ``(x + 0.5) / k - 0.5``
    (:func:`~photonpano.geometry.scale_matrix`).

    Args:
        source: the capture.
        factor: block size k in pixels (>= 1).
        blocks: the block store (see :meth:`__init__`), or None.
        frame_step: :attr:`frame_step` without a store (the block length the run plans
            with, so that its sub-batches are the same with and without the store).

    Raises:
        ValueError: if ``factor`` is not a positive integer no larger than the frame.
    """

    def __init__(self, source: PhotonSource, factor: int, blocks: BinnedBlocks | None = None,
                 frame_step: int = 1) -> None:
        """Wrap ``source``; frames are ``H // factor`` x ``W // factor`` pixels.

        With ``blocks`` (its photons counted once, :class:`BinnedBlocks`), ranges of whole
        blocks are read from there and :attr:`frame_step` is the block length. The sums
        are the same either way (integer counts summed exactly in float32, then scaled).
        """
        factor = int(factor)
        if factor < 1 or factor > min(source.height, source.width):
            raise ValueError(f"binning must be between 1 and the frame size {source.height}x{source.width}, "
                             f"got {factor}")
        self.source, self.factor = source, factor
        self.n_frames, self.exposure_s = source.n_frames, source.exposure_s
        self.frame_rate_hz = source.frame_rate_hz
        self.height, self.width = source.height // factor, source.width // factor
        self.name = f"{source.name} (binned {factor}x{factor})"
        self.kind = getattr(source, "kind", "binary")
        self.blocks = blocks
        self.frame_step = blocks.block if blocks is not None else max(1, int(frame_step))

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.float32]:
        """(B, H // k, W // k) float32 mean detections per sensor pixel over frame ranges ``edges``."""
        edges = np.asarray(edges, np.int64)
        if self.blocks is not None and self.blocks.covers(edges):
            return self.blocks.mean_counts(edges)
        return bin_counts(self.source.sum_ranges(edges), self.factor)

    def __reduce__(self) -> tuple[type, tuple[PhotonSource, int, None, int]]:
        """Pickle as the capture, the binning and the frame step (the block store is this process's file).

        The frame step travels: tasks in other processes then cut the same sub-batches.
        """
        return type(self), (self.source, self.factor, None, self.frame_step)

    def describe(self) -> dict[str, Any]:
        """The underlying capture's summary, with the binning."""
        return {**self.source.describe(), "binning": self.factor}


class RegistrationGrid:
    """Change of coordinates between sensor pixels and the pixels of k x k binned frames.

    Frame-to-panorama homographies ``H`` (sensor pixels of a frame to sensor pixels of
    the middle frame) become ``S H S^-1`` in binned pixels, with ``S`` the (3, 3) map
    from sensor to binned pixel coordinates; a map from frames to a canvas ``C``
    becomes ``C S^-1``.

    Args:
        source: the capture.
        factor: block size k in pixels (1: no binning, every method returns its input).
    """

    def __init__(self, source: PhotonSource, factor: int = 1) -> None:
        """Set up the grid of ``source`` binned ``factor`` x ``factor``."""
        self.factor = int(factor)
        self.source = source if self.factor == 1 else BinnedSource(source, self.factor)
        self.blocks: BinnedBlocks | None = None
        self._counted = False
        self._to_binned = geometry.scale_matrix(1.0 / self.factor)
        self._to_sensor = np.linalg.inv(self._to_binned)

    def count_once(self, boundaries: NDArray[np.int64], group_size: int, executor: Any) -> None:
        """Count the binned photons once for every level (:class:`BinnedBlocks`), where that pays.

        Only the first call counts (the schemes of a run share one grid).

        Only with binning (at full resolution, blocks of 25 frames would shrink a
        packed cube only about three times), binary frames and a block grid of at least
        4 frames that holds every group boundary (:func:`block_size`). The store needs
        an executor of this process; with another (Dask), or if the temporary file
        cannot be written, every level counts from the capture, on the same block grid
        (:attr:`BinnedSource.frame_step`), so that the results do not depend on the
        executor.

        Args:
            boundaries: frame indices where the levels' groups start or stop.
            group_size: binary frames per group m.
            executor: the run's executor.
        """
        import logging

        if self._counted:  # schemes sharing the grid each ask
            return
        self._counted = True
        if self.factor == 1 or self.source.kind != "binary":
            return
        assert isinstance(self.source, BinnedSource)  # factor > 1
        capture = self.source.source
        block = block_size(np.append(boundaries, capture.n_frames), group_size)
        if block < 4:
            return
        self.source = BinnedSource(capture, self.factor, frame_step=block)  # the grid, with or without the store
        if not executor.in_process:
            return
        try:
            blocks = BinnedBlocks(capture, self.factor, block, executor)
        except OSError as err:
            logging.getLogger(__name__).warning("counting photons per level: no room for the binned block "
                                                "store (%s)", err)
            return
        self.blocks = blocks
        self.source = BinnedSource(capture, self.factor, blocks)

    def close(self) -> None:
        """Delete the block store, if any."""
        if self.blocks is not None:
            self.blocks.close()

    def inward(self, homographies: NDArray[np.float64]) -> NDArray[np.float64]:
        """(..., 3, 3) frame-to-panorama homographies in sensor pixels -> binned pixels."""
        if self.factor == 1:
            return homographies
        return geometry.normalize(self._to_binned @ homographies @ self._to_sensor)

    def outward(self, homographies: NDArray[np.float64]) -> NDArray[np.float64]:
        """(..., 3, 3) frame-to-panorama homographies in binned pixels -> sensor pixels."""
        if self.factor == 1:
            return homographies
        return geometry.normalize(self._to_sensor @ homographies @ self._to_binned)

    def located_outward(self, located: LocateResult) -> LocateResult:
        """A scheme's result in sensor pixels: keyframes, registrations (pixel maps between frames), information.

        Only the merged frames it may hold stay binned (they are images of the binned grid).
        """
        if self.factor == 1:
            return located
        import dataclasses

        from ..information import information_in_sensor_pixels

        regs = located.registrations
        regs = dataclasses.replace(regs, homographies=self.outward(regs.homographies))
        cross, chain = located.crosscheck, located.chain
        if cross is not None:
            cross = dataclasses.replace(cross, homographies=self.outward(cross.homographies))
        if chain is not None:
            chain = dataclasses.replace(chain, homographies=self.outward(chain.homographies))
        information = located.information
        if information is not None:
            information = information_in_sensor_pixels(information, self.factor)
        return dataclasses.replace(located, keyframes=self.outward(located.keyframes), registrations=regs,
                                   crosscheck=cross, chain=chain, information=information)
