"""Shared machinery of the built-in warp-and-sum mergers (not a plugin: it registers nothing).

:class:`WarpMerger` runs paper Sec. 4's "Merge" for a level: groups are taken in windows
of consecutive groups, each window's photons are counted once and warped into every
group that holds them (:func:`photonpano.warping.merge_groups`), windows run on the
executor, and a subclass turns each group's warped sums into a merged frame
(:meth:`WarpMerger.estimate`: the flux MLE, or a mean intensity).
"""

from __future__ import annotations

import abc
from typing import Annotated, Any

import numpy as np
from numpy.typing import NDArray
from photonpano.stages import Groups, MergedFrames, Merger, MergerConfig, PhotonSource
from pydantic import Field

__all__ = ["WarpMergeConfig", "WarpMerger"]


class WarpMergeConfig(MergerConfig):
    """Settings shared by the mergers built on :class:`WarpMerger`."""

    subbatch_px: Annotated[float, Field(gt=0, le=2)] = 0.5
    """Consecutive frames whose relative warps differ by less than this many pixels
    (corner travel) are summed before one shared warp: every frame lies within half of
    it from where it belongs, a symmetric blur far below the registration's own noise."""
    min_coverage: Annotated[float, Field(gt=0, le=1)] = 0.8
    """A merged pixel is trusted (given to the locator) when at least this fraction of
    the group's frames observed it."""
    white_percentile: Annotated[float, Field(gt=50, le=100)] = 99.5
    """Tone mapping: this percentile of the merged image (flux or linear intensity) is
    mapped to white."""
    window_groups: Annotated[int, Field(ge=1)] = 8
    """Consecutive groups merged together, their shared photons counted once (memory:
    the window's sub-batch counts, about ``(window_groups - 1) x stride + m`` frames at
    a few MB per 40 frames)."""


class WarpMerger(Merger):
    """Base of the mergers that warp and sum each group's frames (see the module doc).

    Args:
        config: the plugin's :class:`WarpMergeConfig`.
    """

    def __init__(self, config: WarpMergeConfig) -> None:
        self.config = config

    def check_source(self, source: PhotonSource) -> None:
        """Raise :class:`~photonpano.errors.StageError` if ``source`` cannot be merged (default: accept)."""

    @abc.abstractmethod
    def estimate(self, source: PhotonSource, sums: NDArray[np.float32], frames: NDArray[np.float32],
                 n_frames: int) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.uint8]]:
        """Turn one group's warped sums into a merged frame.

        Args:
            source: the capture.
            sums: (H, W) float32 warped detections (or linear intensities) of the group.
            frames: (H, W) float32 number of frames behind each pixel.
            n_frames: frames in the group.

        Returns:
            ``(flux, mask, image)``: (H, W) float32 (NaN where unobserved), bool trusted
            pixels, uint8 tone-mapped image.
        """

    def merge(self, source: PhotonSource, homographies: NDArray[np.float64], groups: Groups,
              progress: Any = None, executor: Any = None) -> MergedFrames:
        """Merge every group (see :meth:`Merger.merge`); windows of groups run on ``executor``."""
        from photonpano.binomial import binary_exposure
        from photonpano.executor import SerialExecutor, pure_task
        from photonpano.warping import merge_groups

        self.check_source(source)
        g, h, w = len(groups), source.height, source.width
        out = MergedFrames(flux=np.empty((g, h, w), np.float32), frames=np.empty((g, h, w), np.float32),
                           images=np.empty((g, h, w), np.uint8), masks=np.empty((g, h, w), bool),
                           exposure_s=binary_exposure(source))
        windows = [np.arange(s, min(s + self.config.window_groups, g)) for s in range(0, g, self.config.window_groups)]

        @pure_task
        def merge_window(index: NDArray[np.int64]) -> tuple[NDArray[np.int64], list[Any]]:
            sums = merge_groups(source, homographies, groups.start[index], groups.stop[index],
                                groups.reference[index], self.config.subbatch_px)
            return index, [(frames, *self.estimate(source, counts, frames, int(groups.stop[i] - groups.start[i])))
                           for i, (counts, frames) in zip(index, sums)]

        done = None if progress is None else (lambda result: progress(len(result[0])))
        for index, merged in (executor or SerialExecutor()).map(merge_window, windows, done=done):
            for i, (frames, flux, mask, image) in zip(index, merged):
                out.frames[i], out.flux[i], out.masks[i], out.images[i] = frames, flux, mask, image
        return out
