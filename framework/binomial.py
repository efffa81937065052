"""The binomial noise of merged binary frames, and a transform that evens it out.

A merged frame's flux is the MLE over ``n`` binary frames (paper Eq. 3); its noise grows
with the flux, so a least-squares registration of flux images is dominated by their
brightest pixels. :func:`stabilised_detections` maps the flux to a scale on which every
pixel's noise is the same; merged frames carry the exposure it needs
(:attr:`MergedFrames.exposure_s <photonpano.records.MergedFrames>`, from
:func:`binary_exposure`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["stabilised_detections", "binary_exposure"]


def stabilised_detections(flux: NDArray, exposure_s: float) -> NDArray[np.float32]:
    """The variance-stabilising transform of a binary frame's detection probability.

    ``arcsin(sqrt(p))`` with ``p = 1 - exp(-phi tau)`` (Anscombe, "The transformation of
    Poisson, binomial and negative-binomial data", Biometrika 35, 1948): the fraction of
    detections over ``n`` binary frames has variance ``p (1 - p) / n``, growing with the
    flux until near saturation, while its transform has variance ``1 / (4 n)`` at every
    flux. A least-squares registration (ECC, Lucas-Kanade) of transformed merged frames
    therefore weighs every pixel by its information, where a registration of flux images
    is dominated by their bright, noisy pixels (the flux MLE's variance grows as
    ``p / (1 - p)``).

    Args:
        flux: float array of flux in photons/s; NaN (unobserved) stays NaN, negative
            values count as 0.
        exposure_s: binary frame exposure ``tau`` in seconds.

    Returns:
        float32 array of the same shape, in radians, within [0, pi/2].
    """
    f = np.asarray(flux, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        out = np.arcsin(np.sqrt(-np.expm1(-np.maximum(f, 0) * np.float32(exposure_s))))
    return np.where(np.isfinite(f), out, np.nan).astype(np.float32)


def binary_exposure(source: Any) -> float | None:
    """A capture's binary frame exposure in seconds, or None for intensity frames (video, counts).

    Merged frames carry it (:class:`~photonpano.records.MergedFrames` ``exposure_s``) so
    that a locator can weigh pixels by their binomial noise (:func:`stabilised_detections`).

    Args:
        source: a capture (:class:`~photonpano.stages.PhotonSource`): its ``kind``
            (``"binary"`` when absent) and ``exposure_s``.

    Returns:
        ``exposure_s`` in seconds for a binary capture, else None.
    """
    return float(source.exposure_s) if getattr(source, "kind", "binary") == "binary" else None
