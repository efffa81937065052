"""Compositor ``flux-canvas``: bilinear warps of sub-batches, flux MLE per canvas pixel.

The panorama as photonpano 0.1 made it: each sub-batch of binary frames is warped onto
the canvas with bilinear interpolation (:class:`photonpano.compose.BilinearCompositor`)
and the flux per canvas pixel is paper Eq. (3). Fast and robust, but bilinear backward
warping blurs by about one frame pixel, so ``scale > 1`` gives a bigger panorama, not a
sharper one; ``drizzle`` is the compositor that resolves sub-pixel detail.
"""

from __future__ import annotations

from typing import Annotated, Literal

from photonpano import hookimpl
from photonpano.compose import BilinearCompositor
from photonpano.robust_merge import DEFAULT_EXPOSURES
from photonpano.stages import CompositorConfig
from pydantic import Field

__all__ = ["FluxCanvasConfig"]


class FluxCanvasConfig(CompositorConfig):
    """Bilinear warps of sub-batches of frames onto the canvas, flux MLE per canvas pixel."""

    plugin: Literal["flux-canvas"] = "flux-canvas"
    robust: bool = False
    """Robust merge: keep ``robust_exposures`` runs of frames apart and leave out those that
    disagree with the static scene at a canvas pixel (a moving object; see
    ``photonpano.robust_merge``); the left-out regions go to ``moving.png``. Off by default
    (``flux-canvas`` is also the mosaic levels' template: ``mosaic.reject_movers`` composites it
    robustly at the first mosaic level to find movers, and while their rejection is engaged)."""
    robust_exposures: Annotated[int, Field(ge=3, le=64)] = DEFAULT_EXPOSURES
    """Virtual exposures the robust merge compares (memory: that many canvases; under a
    flickering lamp, runs of whole periods: up to twice as many)."""

    def build(self) -> BilinearCompositor:
        """Return the compositor at this config's ``scale``."""
        return BilinearCompositor(self.scale, self.robust_exposures if self.robust else None)


@hookimpl
def photonpano_register_compositors() -> list[type[CompositorConfig]]:
    """Register the ``flux-canvas`` compositor."""
    return [FluxCanvasConfig]
