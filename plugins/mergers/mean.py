"""Merger ``mean``: motion-compensated averages of intensity frames.

For conventional high-speed video (``kind == "intensity"`` sources: ``video``,
``photron-mraw``) each frame already holds a linear intensity, so a virtual exposure is
the plain mean of its warped frames (no photon MLE). The frames of a group are warped
into the pixel grid of the group's reference frame with the current homographies, as
``flux-mle`` does (paper Sec. 4, "Merge"), summed, divided by the number of frames
behind each pixel, and tone-mapped for the locator with a configurable curve.

On binary sources the mean is the detection probability per frame (no MLE): usable for
registration, but ``flux-mle`` is the estimator for photon frames.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field

from photonpano import hookimpl
from photonpano.plugins.mergers.flux_mle import WarpMergeConfig
from photonpano.stages import Groups, MergedFrames, Merger, MergerConfig, PhotonSource


class MeanConfig(WarpMergeConfig):
    """Warp-and-average intensity frames per group (conventional high-speed video)."""

    plugin: Literal["mean"] = "mean"
    saturation: Annotated[float, Field(gt=0, le=1)] | None = 0.98
    """Merged pixels whose mean linear intensity reaches this fraction of full scale are
    clipped (no detail, and they hide the true intensity) and not trusted by the
    locator; None trusts them."""
    tone_curve: Literal["srgb", "gamma", "linear"] = "srgb"
    """Curve from linear intensity to the 8-bit images the locator sees: the sRGB curve,
    ``u ** (1 / gamma)``, or none."""
    gamma: Annotated[float, Field(gt=0, le=5)] = 2.2
    """Exponent of the ``gamma`` tone curve."""

    def build(self) -> MeanMerger:
        """Return the merger."""
        return MeanMerger(self)


class MeanMerger(Merger):
    """Merges every group of a level by averaging (see :class:`MeanConfig`).

    The returned :class:`~photonpano.stages.MergedFrames` carry the mean linear
    intensity (relative to full scale) in ``flux``; for binary sources, the mean
    detections per frame.
    """

    def __init__(self, config: MeanConfig) -> None:
        self.config = config

    def tone(self, linear: np.ndarray) -> np.ndarray:
        """Tone-map (H, W) linear values (NaN = unobserved) to a uint8 image."""
        from photonpano.photons import tone_map

        c = self.config
        if c.tone_curve == "srgb":
            return tone_map(linear, percentile=c.white_percentile)
        f = np.asarray(linear, dtype=np.float32)
        seen = np.isfinite(f)
        white = float(np.percentile(f[seen], c.white_percentile)) if seen.any() else 1.0
        u = np.clip(np.where(seen, f, 0) / (white if white > 0 else 1.0), 0, 1)
        if c.tone_curve == "gamma":
            u = u ** (1.0 / c.gamma)
        return np.rint(u * 255).astype(np.uint8)

    def merge(self, source: PhotonSource, homographies: np.ndarray, groups: Groups,
              progress: Any = None, executor: Any = None) -> MergedFrames:
        """Merge each group (see :meth:`Merger.merge`); groups run on ``executor``."""
        from photonpano.intensity import mean_intensity
        from photonpano.plugins.mergers.flux_mle import merge_group

        g, h, w = len(groups), source.height, source.width
        flux = np.empty((g, h, w), np.float32)
        frames = np.empty((g, h, w), np.float32)
        images = np.empty((g, h, w), np.uint8)
        masks = np.empty((g, h, w), bool)

        def merge_one(i: int) -> None:
            start, stop = int(groups.start[i]), int(groups.stop[i])
            sums, frames[i] = merge_group(source, homographies, start, stop, int(groups.reference[i]),
                                          self.config.subbatch_px)
            masks[i] = frames[i] >= self.config.min_coverage * (stop - start)
            flux[i] = mean_intensity(sums, frames[i])
            if self.config.saturation is not None and getattr(source, "kind", "binary") == "intensity":
                masks[i] &= ~(flux[i] >= self.config.saturation)
            images[i] = self.tone(np.where(masks[i], flux[i], np.nan))
            if progress is not None:
                progress(1)

        if executor is None:
            for i in range(g):
                merge_one(i)
        else:
            executor.map(merge_one, range(g))
        return MergedFrames(flux=flux, frames=frames, images=images, masks=masks)


@hookimpl
def photonpano_register_mergers() -> list[type[MergerConfig]]:
    """Register ``mean``."""
    return [MeanConfig]
