"""Drizzle's inverse problem: sliding-DCT Wiener denoising and deconvolution of the fine drops.

A drizzled canvas pixel ``p = S / N`` is the scene seen through two blurs and photon
noise: each drop (a square of one canvas pixel) spreads over the canvas pixels it
overlaps, and the sensor itself samples an interpolated scene (the ``simulate`` source
reads its scene bilinearly at each frame pixel's centre; a real pixel integrates over
its aperture). Per axis the two make a blur close to the cubic B-spline, sampled on the
canvas as ``[a, 1 - 2a, a]`` with ``a = 1/6`` (:data:`DEBLUR`), which keeps a third of
the contrast at the canvas Nyquist frequency; the noise is binomial with variance
``p (1 - p) sharpness / N`` (:mod:`._adaptive`). :func:`restore_sums` estimates the
scene from ``p`` in two steps on overlapping 8x8 blocks of the canvas (a stride of 2),
each block taken to the 2-D DCT-II, where the symmetric blur is (with reflected
borders) diagonal with gain ``h(k) = 1 - 2a + 2a cos(pi k / 8)`` per axis:

1. a pilot: hard thresholding of the coefficients at :data:`HARD_THRESHOLD` noise
   standard deviations (no deblurring);
2. the empirical Wiener filter of the coefficients ``Y`` with the pilot's ``P``:
   ``X = Y h S / (h^2 S + sigma^2)`` with ``S = (P / h)^2`` the pilot's power
   deblurred, so where the pilot shows detail above the noise the blur is inverted
   and where it does not the coefficient is shrunk.

The blocks are put back with the weight ``1 / (sigma^2 sum G^2)`` per block (the
inverse of its noise after filtering) and averaged. This is the two-step DCT
estimator of Yu and Sapiro, "DCT image denoising: a simple and effective image
denoising algorithm", IPOL 1, 2011 (sliding DCT, hard threshold then Wiener, as in
the two steps of BM3D without block matching: Dabov et al., IEEE TIP 16(8), 2007),
with the Wiener step made a deconvolution (a regularised inverse of the known blur, as
in the Wiener deconvolution step of BM3D-deblurring: Dabov et al., SPIE 6812, 2008).
The noise variance per block is the mean of the binomial variance over the block times
:data:`NOISE_FACTOR` (neighbouring canvas pixels share drops, so the noise is
correlated and stronger at the low frequencies than a white noise of that variance).

Measured with the true motion, undersampled capture at ``scale: 2`` (see
docs/performance.md): +4.6 dB above the bilinear merge on average over four
photographs, against +2.4 dB for the noise-adaptive blend of :mod:`._adaptive`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

__all__ = ["DEBLUR", "DEBLUR_SUPER_RESOLVED", "HARD_THRESHOLD", "NOISE_FACTOR", "deblur_for_scale", "restore_sums",
           "dct_wiener"]

DEBLUR = 1.0 / 6.0
"""Per-axis weight ``a`` of the ``[a, 1 - 2a, a]`` blur that the Wiener step inverts
(cubic B-spline: a square drop of one canvas pixel on the canvas grid, convolved with
the sensor's interpolation of the scene). Measured on four photographs, ``scale: 2``,
true motion: ``a = 0`` (denoising only) +2.9 dB, ``1/12`` +3.3 dB, ``1/8`` +4.2 dB,
``1/6`` +4.6 dB, ``5/24`` +4.6 dB above the bilinear merge."""

DEBLUR_SUPER_RESOLVED = 0.2
"""The blur weight at ``scale`` >= 2 (:func:`deblur_for_scale`). There the sensor's own
blur is on the canvas's scale, and the two blurs make the cubic B-spline, whose gain at
the canvas Nyquist frequency (``sinc(1/2)^4``, 0.164) the ``[a, 1 - 2a, a]`` kernel
matches at ``a = 0.209`` (at ``scale: 1`` the drop's triangle alone would give
``sinc(1/2)^2``, ``a = 0.149``; that scale keeps the measured 1/6). Measured with estimated motion on the 15 suite
photographs, undersampled capture at ``scale: 2`` (``benchmarks/super_resolution.py
--photo P --captures undersampled --set compositor.deblur=A``): gain over the bilinear
merge with the true motion, mean / least, 1/6 +3.83 / +2.45 dB, 0.19 +3.96 / +2.51, 0.2
+3.99 / +2.52, 0.22 +3.92 / +2.48, 0.24 +3.24 / +1.68; at ``scale: 1`` (``--captures
standard``) 0.2 lost to 1/6 (mean +6.18 against +6.43 dB, Hubble +2.64 against +3.11)."""


def deblur_for_scale(scale: float) -> float:
    """The default blur weight ``a`` that :func:`dct_wiener` inverts at a super-resolution ``scale``.

    Args:
        scale: canvas pixels per frame pixel (> 0).

    Returns:
        The per-axis weight ``a`` of the ``[a, 1 - 2a, a]`` canvas blur (dimensionless):
        :data:`DEBLUR` at ``scale`` <= 1, :data:`DEBLUR_SUPER_RESOLVED` at ``scale`` >= 2,
        linear in between.
    """
    share = min(max(float(scale) - 1.0, 0.0), 1.0)
    return DEBLUR + share * (DEBLUR_SUPER_RESOLVED - DEBLUR)


HARD_THRESHOLD = 2.7
"""Pilot step: DCT coefficients below this many noise standard deviations are zeroed
(Yu and Sapiro's 3 sigma; 2.0 and 2.7 measured alike, 3.5 lost 0.4 dB)."""

NOISE_FACTOR = 2.0
"""Factor on the mean binomial variance of a block (correlated noise between canvas
pixels that share drops; 1: -0.1 dB, 3: -0.4 dB in the pilot step)."""

BLOCK, STRIDE = 8, 2
"""Block side and stride of the sliding DCT, in canvas pixels."""


def _dct_matrix(n: int) -> NDArray[np.float32]:
    """(n, n) float32 orthonormal DCT-II matrix (rows: frequencies)."""
    k = np.arange(n)
    m = np.cos(np.pi * (2 * k[None, :] + 1) * k[:, None] / (2 * n)) * np.sqrt(2 / n)
    m[0] /= np.sqrt(2)
    return m.astype(np.float32)


def _blocks(image: NDArray[np.float32]) -> NDArray[np.float32]:
    """(By, Bx, BLOCK, BLOCK) view of the blocks at :data:`STRIDE` (image padded to fit)."""
    return np.lib.stride_tricks.sliding_window_view(image, (BLOCK, BLOCK))[::STRIDE, ::STRIDE]


def dct_wiener(noisy: NDArray[np.float32], variance: NDArray[np.float32], deblur: float = DEBLUR,
               hard_threshold: float = HARD_THRESHOLD) -> NDArray[np.float32]:
    """Two-step sliding-DCT estimate of a blurred, noisy image (see the module docstring).

    Args:
        noisy: (H, W) float32 image (here detection probabilities), H, W >= 1.
        variance: (H, W) float32 noise variance per pixel (> 0; large where unobserved).
        deblur: per-axis weight ``a`` in [0, 0.25) of the ``[a, 1 - 2a, a]`` blur to invert
            (0: denoise only).
        hard_threshold: the pilot's threshold in noise standard deviations.

    Returns:
        (H, W) float32 estimate of the sharp image.

    Raises:
        ValueError: if the shapes differ or ``deblur`` is outside [0, 0.25).
    """
    noisy, variance = np.asarray(noisy, np.float32), np.asarray(variance, np.float32)
    if noisy.shape != variance.shape or noisy.ndim != 2:
        raise ValueError(f"dct_wiener: noisy {noisy.shape} and variance {variance.shape} must be one (H, W) shape")
    if not 0 <= deblur < 0.25:
        raise ValueError(f"dct_wiener: deblur must be in [0, 0.25), got {deblur}")
    h, w = noisy.shape
    # pad (reflect) so the blocks at the stride cover the image exactly, at least one block
    ph = max(BLOCK - h, (-(h - BLOCK)) % STRIDE)
    pw = max(BLOCK - w, (-(w - BLOCK)) % STRIDE)
    mode: Literal["reflect", "symmetric"] = "reflect" if min(h, w) > max(ph, pw) else "symmetric"
    y = np.pad(noisy, ((0, ph), (0, pw)), mode=mode)
    v = np.pad(variance, ((0, ph), (0, pw)), mode=mode)
    if min(y.shape) < BLOCK:
        y = np.pad(y, ((0, BLOCK - min(y.shape[0], BLOCK)), (0, BLOCK - min(y.shape[1], BLOCK))), mode="edge")
        v = np.pad(v, ((0, y.shape[0] - v.shape[0]), (0, y.shape[1] - v.shape[1])), mode="edge")
    c = _dct_matrix(BLOCK)
    k = np.arange(BLOCK)
    axis = (1 - 2 * deblur + 2 * deblur * np.cos(np.pi * k / BLOCK)).astype(np.float32)
    gain = np.outer(axis, axis)
    strips = _strips(y.shape[0])
    # step 1: hard-thresholded pilot
    pilot_sum, pilot_weight = np.zeros(y.shape, np.float32), np.zeros(y.shape, np.float32)
    for rows in strips:
        coeffs, sigma2 = _coefficients(y[rows], v[rows], c)
        pilot = np.where(coeffs * coeffs > np.float32(hard_threshold ** 2) * sigma2, coeffs, np.float32(0))
        pilot[..., 0, 0] = coeffs[..., 0, 0]
        _put_back(np.matmul(np.matmul(c.T, pilot), c), _block_weights(pilot != 0, sigma2),
                  pilot_sum[rows], pilot_weight[rows])
    pilot_image = (pilot_sum / np.maximum(pilot_weight, np.float32(1e-30))).astype(np.float32, copy=False)
    # step 2: Wiener deconvolution with the pilot's power
    out_sum, out_weight = pilot_sum, pilot_weight  # reused: the pilot is in ``pilot_image``
    out_sum[:], out_weight[:] = 0, 0
    for rows in strips:
        coeffs, sigma2 = _coefficients(y[rows], v[rows], c)
        power = (np.matmul(np.matmul(c, _blocks(pilot_image[rows])), c.T) / gain) ** 2
        filt = gain * power / (gain * gain * power + sigma2)
        filt[..., 0, 0] = 1 / gain[0, 0]
        _put_back(np.matmul(np.matmul(c.T, coeffs * filt), c), _block_weights(filt, sigma2),
                  out_sum[rows], out_weight[rows])
    return (out_sum / np.maximum(out_weight, np.float32(1e-30)))[:h, :w].astype(np.float32, copy=False)


STRIP_BLOCK_ROWS = 32
"""Rows of blocks transformed at once (bounds the memory to about 1.5 KB per block of a
strip: 64 float32 coefficients in a few arrays)."""


def _strips(height: int) -> list[slice]:
    """Row slices of the padded image, each holding :data:`STRIP_BLOCK_ROWS` rows of blocks (the last fewer)."""
    rows = (height - BLOCK) // STRIDE + 1
    return [slice(r * STRIDE, (min(rows, r + STRIP_BLOCK_ROWS) - 1) * STRIDE + BLOCK)
            for r in range(0, rows, STRIP_BLOCK_ROWS)]


def _coefficients(y: NDArray[np.float32], v: NDArray[np.float32],
                  c: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(By, Bx, 8, 8) DCT coefficients of a strip's blocks and (By, Bx, 1, 1) their noise variance."""
    coeffs = np.matmul(np.matmul(c, _blocks(y)), c.T)
    sigma2 = (_blocks(v).mean(axis=(2, 3)) * np.float32(NOISE_FACTOR))[..., None, None]
    return coeffs, sigma2


def _block_weights(filt: NDArray, sigma2: NDArray[np.float32]) -> NDArray[np.float32]:
    """(By, Bx) float32 aggregation weights: the inverse of each block's noise after ``filt``."""
    energy = np.maximum(np.square(filt, dtype=np.float32).sum(axis=(2, 3)), np.float32(1))
    return (1 / (energy * sigma2[..., 0, 0] + np.float32(1e-12))).astype(np.float32)


def _put_back(blocks: NDArray[np.float32], weights: NDArray[np.float32], out: NDArray[np.float32],
              acc: NDArray[np.float32]) -> None:
    """Add (By, Bx, BLOCK, BLOCK) blocks times their (By, Bx) weights into ``out`` and the weights into ``acc``."""
    by, bx = weights.shape
    weighted = blocks * weights[..., None, None]
    for i in range(BLOCK):
        for j in range(BLOCK):
            out[i:i + by * STRIDE:STRIDE, j:j + bx * STRIDE:STRIDE] += weighted[:, :, i, j]
            acc[i:i + by * STRIDE:STRIDE, j:j + bx * STRIDE:STRIDE] += weights


def restore_sums(sums: NDArray[np.float32], frames: NDArray[np.float32], scale: float, wide_px: float,
                 sharpness: float, deblur: float = DEBLUR) -> NDArray[np.float32]:
    """Drizzle's sums with the fine detection probability denoised and deblurred.

    Args:
        sums: (Hc, Wc) float32 drop-weighted detections S per canvas pixel.
        frames: (Hc, Wc) float32 drop-weighted binary frames N per canvas pixel.
        scale: canvas pixels per frame pixel.
        wide_px: half-width in frame pixels of the wide tent whose probability sets the
            binomial noise variance (:func:`._adaptive.fine_and_noise`).
        sharpness: :func:`._adaptive.drop_sharpness` of the drops.
        deblur: see :func:`dct_wiener`.

    Returns:
        (Hc, Wc) float32 detections ``p_out N`` to put in place of ``sums`` (0 where
        ``N == 0``), ``p_out`` clipped to [0, 1].
    """
    from ._adaptive import fine_and_noise

    p, p_wide, noise = fine_and_noise(sums, frames, scale, wide_px, sharpness)
    seen = frames > 0
    if seen.any() and not seen.all():
        # unobserved canvas pixels (holes between drops, beyond the coverage) take the wide
        # estimate of the nearest observed one: zeros there would pull the blocks around them dark
        from scipy.ndimage import distance_transform_edt

        nearest = distance_transform_edt(~seen, return_distances=False, return_indices=True)
        p_wide = p_wide[nearest[0], nearest[1]]
    p = np.where(seen, p, p_wide)
    noise = np.where(seen, noise, np.float32(0.25))  # unobserved: a sample's whole variance
    noise = np.maximum(noise, np.float32(1e-9))
    restored = np.clip(dct_wiener(p, noise, deblur), 0, 1)
    return np.where(seen, restored * frames, np.float32(0)).astype(np.float32)
