"""Merger ``flux-mle``: motion-compensated virtual exposures from binary frames.

Paper Sec. 4, "Merge": the frames of each group are warped by the current per-frame
homographies *relative to the group's reference (centre) frame*, so each frame moves by
a small amount only; the warped detections are summed and the flux is estimated with
Eq. (3), ``phi = -ln(1 - S/n) / tau``, then tone-mapped to 8-bit sRGB for the locator.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.plugins.mergers.common import WarpMergeConfig, WarpMerger
from photonpano.stages import MergerConfig, PhotonSource


class FluxMLEConfig(WarpMergeConfig):
    """Warp-and-sum binary frames per group, then the flux MLE (paper Eq. 3)."""

    plugin: Literal["flux-mle"] = "flux-mle"

    def build(self) -> FluxMLEMerger:
        """Return the merger."""
        return FluxMLEMerger(self)


class FluxMLEMerger(WarpMerger):
    """Merges every group of a level (see :class:`FluxMLEConfig`)."""

    def check_source(self, source: PhotonSource) -> None:
        """Refuse intensity sources (their frames hold no photon detections)."""
        if getattr(source, "kind", "binary") != "binary":
            from photonpano.errors import StageError

            raise StageError("merger", "flux-mle", f"{source.name} holds intensity frames, not photon "
                             "detections; use merger: mean")

    def estimate(self, source: PhotonSource, sums: NDArray[np.float32], frames: NDArray[np.float32],
                 n_frames: int) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.uint8]]:
        """Flux MLE (paper Eq. 3) per pixel, trusted mask and tone-mapped image (see :meth:`WarpMerger.estimate`)."""
        from photonpano.photons import flux_mle, tone_map

        mask = frames >= self.config.min_coverage * n_frames
        flux = flux_mle(sums, frames, source.exposure_s)
        return flux, mask, tone_map(np.where(mask, flux, np.nan), percentile=self.config.white_percentile)


@hookimpl
def photonpano_register_mergers() -> list[type[MergerConfig]]:
    """Register ``flux-mle``."""
    return [FluxMLEConfig]
