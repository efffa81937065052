"""The phase-correlation locator (numpy only).

For frames a and b with ``b(x) = a(x + t)`` (so the homography from b's pixels to a's is
the translation ``t``), the normalised cross-power spectrum ``A conj(B) / |A conj(B)|``
is ``exp(-2 pi i f.t)``, whose inverse FFT peaks at ``+t``. Weighting the spectrum by a
Gaussian makes the peak a Gaussian, located to sub-pixel precision by a parabola through
the logarithm of the peak and its neighbours along each axis.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from photonpano.stages import Locator, LocatorContext, MergedFrames, PairRegistrations

from .plugin import PhaseCorrConfig

__all__ = ["PhaseCorrLocator", "phase_correlation", "register_translation"]


def _prepare(flux: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Zero-mean image with unobserved pixels at the mean."""
    trusted = mask & np.isfinite(flux)
    image = np.where(trusted, flux, np.nan).astype(np.float64)
    mean = float(np.nanmean(image)) if trusted.any() else 0.0
    return np.where(trusted, image, mean) - mean


def _shift(image: NDArray[np.float64], tx: float, ty: float) -> NDArray[np.float64]:
    """Return ``image(x - t)`` (content moved by ``+t``) by the Fourier shift theorem."""
    h, w = image.shape
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(image) * np.exp(-2j * np.pi * (fx * tx + fy * ty))))


def register_translation(a: NDArray[np.float64], b: NDArray[np.float64], *, window: bool = True,
                         blur_px: float = 1.0, iterations: int = 3) -> tuple[float, float, float]:
    """Return the shift ``t`` with ``b(x) = a(x + t)`` and the peak response.

    Windowing biases phase correlation towards zero shift, so the estimate is refined:
    b is shifted back by the current estimate and the residual is measured again.

    Args:
        a: (H, W) float64 zero-mean image.
        b: (H, W) float64 zero-mean image.
        window: apply a Hann window before each correlation.
        blur_px: see :func:`phase_correlation`.
        iterations: correlations in all (1 = plain phase correlation).

    Returns:
        ``(tx, ty, response)`` as :func:`phase_correlation`, response of the first pass.
    """
    taper = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1])) if window else 1.0
    tx = ty = 0.0
    response = 0.0
    for i in range(iterations):
        moved = _shift(b, tx, ty) if i else b
        dx, dy, r = phase_correlation(a * taper, moved * taper, blur_px)
        if i == 0:
            response = r
            if r <= 0:
                break
        tx, ty = tx + dx, ty + dy
    return tx, ty, response


def phase_correlation(a: NDArray[np.float64], b: NDArray[np.float64], blur_px: float = 1.0
                      ) -> tuple[float, float, float]:
    """Return the shift ``t`` with ``b(x) = a(x + t)`` and the peak response.

    Args:
        a: (H, W) float64 zero-mean image.
        b: (H, W) float64 zero-mean image.
        blur_px: Gaussian low-pass of the correlation surface, standard deviation in pixels.

    Returns:
        ``(tx, ty, response)``: the shift in pixels (x right, y down) and the peak of
        the normalised correlation surface (0 for unrelated or blank frames).
    """
    h, w = a.shape
    cross = np.fft.fft2(a) * np.conj(np.fft.fft2(b))
    magnitude = np.abs(cross)
    if not np.any(magnitude > 1e-12 * max(float(magnitude.max()), 1e-300)) or magnitude.max() == 0:
        return 0.0, 0.0, 0.0
    cross = cross / np.maximum(magnitude, 1e-12 * magnitude.max())
    response = float(np.real(np.fft.ifft2(cross)).max())
    if blur_px > 0:
        fy, fx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]
        cross *= np.exp(-2 * (np.pi * blur_px) ** 2 * (fx ** 2 + fy ** 2))
    surface = np.real(np.fft.ifft2(cross))
    peak = np.unravel_index(int(np.argmax(surface)), surface.shape)
    offsets = []
    for axis, size in ((1, w), (0, h)):
        idx = list(peak)
        values = []
        for d in (-1, 0, 1):
            idx[axis] = (peak[axis] + d) % size
            values.append(np.log(max(surface[tuple(idx)], 1e-12 * surface[peak])))
        denom = values[0] - 2 * values[1] + values[2]
        frac = 0.5 * (values[0] - values[2]) / denom if denom < 0 else 0.0
        shift = peak[axis] + float(np.clip(frac, -0.5, 0.5))
        offsets.append(shift - size if shift > size / 2 else shift)
    return offsets[0], offsets[1], response


class PhaseCorrLocator(Locator):
    """Registers pairs of merged frames by phase correlation (translation only).

    ``initial`` is not used (phase correlation is global). ``matches`` is 0 and
    ``inliers`` the number of pixels the two frames share at the found shift.
    """

    def __init__(self, config: PhaseCorrConfig) -> None:
        self.config = config

    def _register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64], initial: NDArray[np.float64],
                        context: LocatorContext) -> PairRegistrations:
        """Register each pair (see :meth:`photonpano.stages.Locator.register_pairs`, which validated them).

        The public method resolved the pairs' frame ids: ``merged`` holds the frames they
        name and ``pairs`` are (P, 2) int64 positions in it.
        """
        prepared: dict[int, NDArray[np.float64]] = {}

        def image(i: int) -> NDArray[np.float64]:
            if i not in prepared:
                prepared[i] = _prepare(merged.flux[i], merged.masks[i])
            return prepared[i]

        h, w = merged.flux.shape[1:]
        homographies = np.repeat(np.eye(3)[None], len(pairs), axis=0)
        inliers = np.zeros(len(pairs), np.int64)
        ok = np.zeros(len(pairs), bool)
        for p, (a, b) in enumerate(pairs):
            tx, ty, response = register_translation(image(int(a)), image(int(b)), window=self.config.window,
                                                    blur_px=self.config.peak_blur_px)
            ok[p] = response >= self.config.min_response and abs(tx) < w / 2 and abs(ty) < h / 2
            if ok[p]:
                homographies[p, 0, 2], homographies[p, 1, 2] = tx, ty
                inliers[p] = int(max(w - abs(tx), 0) * max(h - abs(ty), 0))
        return PairRegistrations(homographies=homographies, matches=np.zeros(len(pairs), np.int64),
                                 inliers=inliers, ok=ok)
