"""Registration of the ``phasecorr`` locator: the module named by the entry point.

Keep this module cheap to import: photonpano imports it to list and validate plugins.
The working code lives in ``_impl`` and is imported by :meth:`PhaseCorrConfig.build`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from photonpano import hookimpl
from photonpano.stages import Locator, LocatorConfig
from pydantic import Field

__all__ = ["PhaseCorrConfig", "photonpano_register_locators"]


class PhaseCorrConfig(LocatorConfig):
    """Translation-only registration by phase correlation (numpy FFT, sub-pixel peak)."""

    plugin: Literal["phasecorr"] = "phasecorr"
    min_response: Annotated[float, Field(gt=0, lt=1)] = 0.05
    """Peak height of the normalised cross-power spectrum's inverse below which a pair is
    flagged as failed (dimensionless; 1 for identical frames)."""
    window: bool = True
    """Apply a Hann window before the FFT (suppresses the frame edges' spectral leakage)."""
    peak_blur_px: Annotated[float, Field(ge=0)] = 1.0
    """Standard deviation, in pixels, of the Gaussian that weights the cross-power
    spectrum (a low-pass; 0 = none): it widens and steadies the correlation peak of noisy
    frames, which the sub-pixel fit needs."""

    def build(self) -> Locator:
        """Return the locator (the implementation is imported only now)."""
        from ._impl import PhaseCorrLocator

        return PhaseCorrLocator(self)


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Offer the ``phasecorr`` locator."""
    return [PhaseCorrConfig]
