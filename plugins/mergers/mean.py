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

from typing import Annotated, Literal

import numpy as np
from photonpano import hookimpl
from photonpano.plugins.mergers.common import WarpMergeConfig, WarpMerger
from photonpano.stages import MergerConfig, PhotonSource
from pydantic import Field


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


class MeanMerger(WarpMerger):
    """Merges every group of a level by averaging (see :class:`MeanConfig`).

    The returned :class:`~photonpano.stages.MergedFrames` carry the mean linear
    intensity (relative to full scale) in ``flux``; for binary sources, the mean
    detections per frame.
    """

    config: MeanConfig  # built by MeanConfig.build

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

    def estimate(self, source: PhotonSource, sums: np.ndarray, frames: np.ndarray,
                 n_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mean linear intensity per pixel, trusted mask (saturation excluded) and image.

        See :meth:`WarpMerger.estimate`.
        """
        from photonpano.intensity import mean_intensity

        mask = frames >= self.config.min_coverage * n_frames
        flux = mean_intensity(sums, frames)
        if self.config.saturation is not None and getattr(source, "kind", "binary") == "intensity":
            mask &= ~(flux >= self.config.saturation)
        return flux, mask, self.tone(np.where(mask, flux, np.nan))


@hookimpl
def photonpano_register_mergers() -> list[type[MergerConfig]]:
    """Register ``mean``."""
    return [MeanConfig]
