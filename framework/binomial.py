"""The binomial noise of merged binary frames, and a transform that evens it out.

A merged frame's flux is the MLE over ``n`` binary frames (paper Eq. 3); its noise grows
with the flux, so a least-squares registration of flux images is dominated by their
brightest pixels. :func:`stabilised_detections` maps the flux to a scale on which every
pixel's noise is the same; merged frames carry the exposure it needs
(:attr:`MergedFrames.exposure_s <photonpano.records.MergedFrames>`, from
:func:`binary_exposure`).
"""

from __future__ import annotations

import functools
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
        float32 array of the same shape, in radians, within [0, pi/2]; NaN where ``flux``
        is not finite. Computed by a compiled, linearly interpolated table of the
        transform in ``sqrt(flux tau)``, within 3.5e-8 of it (``photonpano._binomial_compiled``:
        ten times faster than numpy's scalar ``expm1`` and ``arcsin``).
    """
    from ._binomial_compiled import TABLE_END, TABLE_INTERVALS, stabilise_kernel

    f = np.ascontiguousarray(flux, dtype=np.float32)
    out = np.empty(f.shape, np.float32)
    stabilise_kernel(f.reshape(-1), np.float32(exposure_s), _table(), TABLE_INTERVALS / TABLE_END, out.reshape(-1))
    return out


@functools.cache
def _table() -> NDArray[np.float64]:
    """The transform's table, built once per process (``photonpano._binomial_compiled.transform_table``)."""
    from ._binomial_compiled import transform_table

    return transform_table()


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
