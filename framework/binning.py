"""Registration at a binned resolution: the capture seen through k x k pixel binning.

Motion is estimated on merged frames, and the locators register them at a fraction of
the sensor resolution anyway (SIFT detects on half-resolution frames, ECC against the
panorama stops at its half-resolution pyramid level). Merging them at that resolution
in the first place, by summing the photons of k x k sensor pixels (*binning*, as a
camera's readout does), gives the locators the same images for a k^2-th of the
warping, flux and tone-mapping work.

:class:`RegistrationGrid` is the change of coordinates between the sensor's pixels and
the binned ones; the level loop (:func:`photonpano.levels.estimate_motion`) hands its
schemes the binned capture and binned homographies and turns their keyframes back into
sensor pixels, so schemes, mergers and locators need not know about binning. The
panorama is composited from the full-resolution photons.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .records import LocateResult, Panorama
from .stages import PhotonSource

__all__ = ["BinnedSource", "RegistrationGrid", "bin_counts", "auto_binning", "registration_binning", "MIN_BINNED_SIDE"]

MIN_BINNED_SIDE = 100
"""``registration_binning: auto`` bins only where the binned frames keep at least this many
pixels on their short side: registration precision comes from the number of pixels, and
on smaller frames (127x248, the super-resolution benchmark's) binning doubled the
trajectory error (0.10 -> 0.22 px)."""


def auto_binning(height: int, width: int) -> int:
    """The binning of ``registration_binning: auto``: 2 if frames stay >= :data:`MIN_BINNED_SIDE` pixels, else 1.

    Args:
        height: frame height in sensor pixels.
        width: frame width in sensor pixels.
    """
    return 2 if min(height, width) // 2 >= MIN_BINNED_SIDE else 1


def registration_binning(spec: Any, source: PhotonSource) -> int:
    """The spec's ``registration_binning`` for ``source`` (``auto`` resolved by :func:`auto_binning`).

    Raises:
        StageError: if the binning leaves frames smaller than 16 pixels.
    """
    from .errors import StageError

    value = spec.registration_binning
    factor = auto_binning(source.height, source.width) if value == "auto" else int(value)
    if min(source.height, source.width) // factor < 16:
        raise StageError("spec", "registration_binning", f"binning {factor}x{factor} leaves frames of "
                         f"{source.height}x{source.width} pixels smaller than 16 pixels")
    return factor


def bin_counts(counts: NDArray, factor: int) -> NDArray[np.float32]:
    """Mean of each ``factor`` x ``factor`` block of pixels of B count images.

    Args:
        counts: (B, H, W) detection counts (any real dtype).
        factor: block size k in pixels (>= 1).

    Returns:
        (B, H // k, W // k) float32 mean count per sensor pixel of each block (the
        last ``H % k`` rows and ``W % k`` columns are left out).
    """
    b, h, w = counts.shape
    k = int(factor)
    hb, wb = h // k, w // k
    out = np.zeros((b, hb, wb), np.float32)
    for dy in range(k):
        rows = counts[:, dy:hb * k:k]
        for dx in range(k):
            out += rows[:, :, dx:wb * k:k]
    out *= np.float32(1.0 / (k * k))
    return out


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

    Raises:
        ValueError: if ``factor`` is not a positive integer no larger than the frame.
    """

    def __init__(self, source: PhotonSource, factor: int) -> None:
        """Wrap ``source``; frames are ``H // factor`` x ``W // factor`` pixels."""
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

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.float32]:
        """(B, H // k, W // k) float32 mean detections per sensor pixel over frame ranges ``edges``."""
        return bin_counts(self.source.sum_ranges(edges), self.factor)

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
        self._to_binned = geometry.scale_matrix(1.0 / self.factor)
        self._to_sensor = np.linalg.inv(self._to_binned)

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

    def template_inward(self, template: Panorama | None) -> Panorama | None:
        """A panorama whose homographies map sensor frames -> one mapping binned frames (same canvas)."""
        if template is None or self.factor == 1:
            return template
        return Panorama(template.flux, template.frames, geometry.normalize(template.homographies @ self._to_sensor))

    def template_outward(self, template: Panorama | None) -> Panorama | None:
        """The inverse of :meth:`template_inward`."""
        if template is None or self.factor == 1:
            return template
        return Panorama(template.flux, template.frames, geometry.normalize(template.homographies @ self._to_binned))

    def located_outward(self, located: LocateResult) -> LocateResult:
        """A scheme's result in sensor pixels: keyframes, registrations (pixel maps between frames) and template.

        Only the merged frames it may hold stay binned (they are images of the binned grid).
        """
        if self.factor == 1:
            return located
        import dataclasses

        regs = located.registrations
        regs = dataclasses.replace(regs, homographies=self.outward(regs.homographies))
        return dataclasses.replace(located, keyframes=self.outward(located.keyframes), registrations=regs,
                                   template=self.template_outward(located.template))
