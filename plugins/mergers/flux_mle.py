"""Merger ``flux-mle``: motion-compensated virtual exposures from binary frames.

Paper Sec. 4, "Merge": the frames of each group are warped by the current per-frame
homographies *relative to the group's reference (centre) frame*, so each frame moves by
a small amount only; the warped detections are summed and the flux is estimated with
Eq. (3), ``phi = -ln(1 - S/n) / tau``, then tone-mapped to 8-bit sRGB for the locator.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from photonpano import hookimpl
from photonpano.executor import Executor
from photonpano.stages import Groups, MergedFrames, Merger, MergerConfig, PhotonSource


class WarpMergeConfig(MergerConfig):
    """Settings shared by the mergers that warp a group's frames with :func:`merge_group`."""

    subbatch_px: Annotated[float, Field(gt=0, le=2)] = 0.25
    """Consecutive frames whose relative warps differ by less than this many pixels
    (corner travel) are summed before one shared warp."""
    min_coverage: Annotated[float, Field(gt=0, le=1)] = 0.8
    """A merged pixel is trusted (given to the locator) when at least this fraction of
    the group's frames observed it."""
    white_percentile: Annotated[float, Field(gt=50, le=100)] = 99.5
    """Tone mapping: this percentile of the merged image (flux or linear intensity) is
    mapped to white."""


class FluxMLEConfig(WarpMergeConfig):
    """Warp-and-sum binary frames per group, then the flux MLE (paper Eq. 3)."""

    plugin: Literal["flux-mle"] = "flux-mle"

    def build(self) -> FluxMLEMerger:
        """Return the merger."""
        return FluxMLEMerger(self)


def merge_group(source: PhotonSource, homographies: NDArray[np.float64], start: int, stop: int,
                reference: int, subbatch_px: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Warp the frames ``start:stop`` into the pixel grid of frame ``reference`` and sum.

    Args:
        source: the capture.
        homographies: (T, 3, 3) float64 current frame-to-panorama homographies.
        start: first frame of the group.
        stop: one past its last frame.
        reference: frame whose pixel grid receives the group.
        subbatch_px: sub-batch tolerance in pixels (see :func:`subbatch_edges`).

    Returns:
        ``(counts, frames)``: (H, W) float32 warped detections and number of frames per
        pixel.
    """
    from photonpano.warping import WarpAccumulator, subbatch_edges

    relative = np.linalg.inv(homographies[reference]) @ homographies[start:stop]
    edges = subbatch_edges(relative, source.width, source.height, subbatch_px)
    counts = source.sum_ranges(start + edges)
    acc = WarpAccumulator(source.height, source.width)
    for b in range(len(edges) - 1):
        middle = (edges[b] + edges[b + 1]) // 2
        acc.add(counts[b], int(edges[b + 1] - edges[b]), relative[middle])
    return acc.counts, acc.frames


class FluxMLEMerger(Merger):
    """Merges every group of a level (see :class:`FluxMLEConfig`)."""

    def __init__(self, config: FluxMLEConfig) -> None:
        self.config = config

    def merge(self, source: PhotonSource, homographies: NDArray[np.float64], groups: Groups,
              progress: Any = None, executor: Executor | None = None) -> MergedFrames:
        """Merge each group (see :meth:`Merger.merge`); groups run on ``executor``."""
        from photonpano.executor import SerialExecutor
        from photonpano.photons import flux_mle, tone_map

        if getattr(source, "kind", "binary") != "binary":
            from photonpano.errors import StageError

            raise StageError("merger", "flux-mle", f"{source.name} holds intensity frames, not photon "
                             "detections; use merger: mean")
        g, h, w = len(groups), source.height, source.width
        flux = np.empty((g, h, w), np.float32)
        frames = np.empty((g, h, w), np.float32)
        images = np.empty((g, h, w), np.uint8)
        masks = np.empty((g, h, w), bool)

        def merge_one(i: int) -> None:
            start, stop = int(groups.start[i]), int(groups.stop[i])
            counts, frames[i] = merge_group(source, homographies, start, stop,
                                            int(groups.reference[i]), self.config.subbatch_px)
            masks[i] = frames[i] >= self.config.min_coverage * (stop - start)
            flux[i] = flux_mle(counts, frames[i], source.exposure_s)
            images[i] = tone_map(np.where(masks[i], flux[i], np.nan), percentile=self.config.white_percentile)
            if progress is not None:
                progress(1)

        (executor or SerialExecutor()).map(merge_one, range(g))
        return MergedFrames(flux=flux, frames=frames, images=images, masks=masks)


@hookimpl
def photonpano_register_mergers() -> list[type[MergerConfig]]:
    """Register ``flux-mle``."""
    return [FluxMLEConfig]
