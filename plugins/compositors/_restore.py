"""Drizzle's inverse problem: sliding-DCT Wiener denoising and deconvolution of the fine drops.

A drizzled canvas pixel ``p = S / N`` is the scene seen through two blurs and photon
noise: each drop (a square of one canvas pixel) spreads over the canvas pixels it
overlaps, and the sensor itself samples an interpolated scene (the ``simulate`` source
reads its scene bilinearly at each frame pixel's centre; a real pixel integrates over
its aperture). Per axis the two make a blur close to the cubic B-spline, sampled on the
canvas as ``[a, 1 - 2a, a]`` with ``a = 1/6`` (:data:`DEBLUR`), which keeps a third of
the contrast at the canvas Nyquist frequency; the noise is binomial with variance
``p (1 - p) sharpness / N`` (:mod:`._adaptive`). :func:`restore_sums` estimates the
scene from ``p`` in two steps on every 8x8 block of the canvas (a stride of 1: each
pixel is estimated in 64 blocks), each block taken to the 2-D DCT-II, where the
symmetric blur is (with reflected borders) diagonal with gain
``h(k) = 1 - 2a + 2a cos(pi k / 8)`` per axis:

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

The DCT is separable, so the blocks at every position share their row and column
transforms (:func:`_forward`, :func:`_inverse_add`: each a sliding window and one matrix
product): stride 1 costs 1.6 times what the former stride of 2 did (a 600 x 2400
canvas: 1.2 s against 0.74; the per-block transforms at stride 1: about 3.2 s), and
gains over it on every suite photograph (``benchmarks/super_resolution.py``, estimated
motion; docs/performance.md, "The sliding DCT at every position"): at ``scale: 2`` on
the undersampled capture the mean gain over the bilinear merge with the true motion
went from +3.99 to +4.12 dB and the least (handwriting) from +2.52 to +2.69; at
``scale: 1`` from +6.43 to +6.91 dB, the least from +3.11 (Hubble) to +3.64.

Measured with the true motion, undersampled capture at ``scale: 2`` (see
docs/performance.md): +4.6 dB above the bilinear merge on average over four
photographs, against +2.4 dB for the noise-adaptive blend of :mod:`._adaptive`
(at a stride of 2).
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

BLOCK = 8
"""Block side of the sliding DCT, in canvas pixels. Every block position is used (a stride
of 1), so each canvas pixel is estimated in 64 blocks."""


def _dct_matrix(n: int) -> NDArray[np.float32]:
    """(n, n) float32 orthonormal DCT-II matrix (rows: frequencies)."""
    k = np.arange(n)
    m = np.cos(np.pi * (2 * k[None, :] + 1) * k[:, None] / (2 * n)) * np.sqrt(2 / n)
    m[0] /= np.sqrt(2)
    return m.astype(np.float32)


def dct_wiener(noisy: NDArray[np.float32], variance: NDArray[np.float32],
               deblur: float | tuple[float, float] = DEBLUR, hard_threshold: float = HARD_THRESHOLD
               ) -> NDArray[np.float32]:
    """Two-step sliding-DCT estimate of a blurred, noisy image (see the module docstring).

    Args:
        noisy: (H, W) float32 image (here detection probabilities), H, W >= 1.
        variance: (H, W) float32 noise variance per pixel (> 0; large where unobserved).
        deblur: weight ``a`` in [0, 0.25) of the ``[a, 1 - 2a, a]`` blur to invert along
            each axis, or ``(horizontal, vertical)`` weights (0: denoise only).
        hard_threshold: the pilot's threshold in noise standard deviations.

    Returns:
        (H, W) float32 estimate of the sharp image.

    Raises:
        ValueError: if the shapes differ or a ``deblur`` weight is outside [0, 0.25).
    """
    noisy, variance = np.asarray(noisy, np.float32), np.asarray(variance, np.float32)
    if noisy.shape != variance.shape or noisy.ndim != 2:
        raise ValueError(f"dct_wiener: noisy {noisy.shape} and variance {variance.shape} must be one (H, W) shape")
    across, down = (float(deblur), float(deblur)) if isinstance(deblur, (int, float)) else map(float, deblur)
    if not (0 <= across < 0.25 and 0 <= down < 0.25):
        raise ValueError(f"dct_wiener: deblur must be in [0, 0.25), got {deblur}")
    h, w = noisy.shape
    # an image smaller than a block is mirrored to one (its edge repeated where that is not enough)
    ph, pw = max(BLOCK - h, 0), max(BLOCK - w, 0)
    mode: Literal["reflect", "symmetric"] = "reflect" if min(h, w) > max(ph, pw) else "symmetric"
    y = np.pad(noisy, ((0, ph), (0, pw)), mode=mode)
    v = np.pad(variance, ((0, ph), (0, pw)), mode=mode)
    if min(y.shape) < BLOCK:
        y = np.pad(y, ((0, BLOCK - min(y.shape[0], BLOCK)), (0, BLOCK - min(y.shape[1], BLOCK))), mode="edge")
        v = np.pad(v, ((0, y.shape[0] - v.shape[0]), (0, y.shape[1] - v.shape[1])), mode="edge")
    c = _dct_matrix(BLOCK)
    cosine = np.cos(np.pi * np.arange(BLOCK) / BLOCK)
    # coefficients are indexed [..., horizontal frequency, vertical frequency] (_forward)
    gain = np.outer(1 - 2 * across + 2 * across * cosine, 1 - 2 * down + 2 * down * cosine).astype(np.float32)
    strips = [slice(first, last + BLOCK - 1)  # the image rows of each strip of block rows
              for first, last in _strips(y.shape[0] - BLOCK + 1, y.shape[1] - BLOCK + 1)]
    # step 1: hard-thresholded pilot
    pilot_sum, pilot_weight = np.zeros(y.shape, np.float32), np.zeros(y.shape, np.float32)
    for rows in strips:
        coeffs, sigma2 = _forward(y[rows], c), _block_noise(v[rows])
        keep = coeffs * coeffs > np.float32(hard_threshold ** 2) * sigma2[..., None, None]
        keep[..., 0, 0] = True
        coeffs[~keep] = 0
        kept = np.maximum(keep.sum(axis=(2, 3), dtype=np.float32), np.float32(1))
        _inverse_add(coeffs, 1 / (kept * sigma2 + np.float32(1e-12)), c, pilot_sum[rows], pilot_weight[rows])
    pilot_image = (pilot_sum / np.maximum(pilot_weight, np.float32(1e-30))).astype(np.float32, copy=False)
    # step 2: Wiener deconvolution with the pilot's power
    out_sum, out_weight = pilot_sum, pilot_weight  # reused: the pilot is in ``pilot_image``
    out_sum[:], out_weight[:] = 0, 0
    for rows in strips:
        noise = _block_noise(v[rows])[..., None, None]
        power = np.square(_forward(pilot_image[rows], c))  # the pilot's power blurred: gain^2 S
        filt = power / ((power + noise) * gain)  # gain S / (gain^2 S + sigma^2)
        filt[..., 0, 0] = 1 / gain[0, 0]
        energy = np.maximum(np.square(filt).sum(axis=(2, 3)), np.float32(1))
        coeffs = _forward(y[rows], c)
        coeffs *= filt
        _inverse_add(coeffs, 1 / (energy * noise[..., 0, 0] + np.float32(1e-12)), c, out_sum[rows], out_weight[rows])
    return (out_sum / np.maximum(out_weight, np.float32(1e-30)))[:h, :w].astype(np.float32, copy=False)


STRIP_BLOCKS = 16_384
"""Block positions transformed at once (about 4 MB per array of their 64 float32
coefficients; smaller strips stay in cache: on a 600 x 2400 canvas 8 rows of blocks took
1.15 s, 32 rows 1.39 s, 64 rows 2.08 s)."""


def _strips(rows: int, columns: int) -> list[tuple[int, int]]:
    """``(first, last)`` block rows of each strip: about :data:`STRIP_BLOCKS` positions of ``rows`` x ``columns``."""
    step = max(1, STRIP_BLOCKS // max(columns, 1))
    return [(first, min(rows, first + step)) for first in range(0, rows, step)]


def _block_noise(variance: NDArray[np.float32]) -> NDArray[np.float32]:
    """(R, W - 7) float32 each block's noise variance, from a strip's (R + 7, W) ``variance``.

    The mean over the block times :data:`NOISE_FACTOR`, from running sums in float64.
    """
    total = np.zeros((variance.shape[0] + 1, variance.shape[1] + 1), np.float64)
    np.cumsum(np.cumsum(variance, axis=0, dtype=np.float64), axis=1, out=total[1:, 1:])
    sums = total[BLOCK:, BLOCK:] - total[:-BLOCK, BLOCK:] - total[BLOCK:, :-BLOCK] + total[:-BLOCK, :-BLOCK]
    return (sums * (NOISE_FACTOR / BLOCK ** 2)).astype(np.float32)


def _forward(rows: NDArray[np.float32], c: NDArray[np.float32]) -> NDArray[np.float32]:
    """(R, W - 7, 8, 8) float32 2-D DCT-II of every block of ``rows`` ((R + 7, W) image rows), index ``[y, x, v, u]``.

    Separable: each row's sliding 8-pixel windows first (the horizontal frequency ``v``),
    then 8 rows of those (the vertical frequency ``u``); the same coefficients as each
    block's ``c @ block @ c.T`` transposed, for an eighth of the row work.
    """
    along_rows = np.lib.stride_tricks.sliding_window_view(rows, BLOCK, axis=1) @ c.T  # (R + 7, W - 7, v)
    return np.lib.stride_tricks.sliding_window_view(along_rows, BLOCK, axis=0) @ c.T


def _inverse_add(coeffs: NDArray[np.float32], weights: NDArray[np.float32], c: NDArray[np.float32],
                 out: NDArray[np.float32], acc: NDArray[np.float32]) -> None:
    """Add each block's inverse DCT times its weight into ``out``, and the weights into ``acc``.

    Args:
        coeffs: (R, W - 7, 8, 8) float32 coefficients as :func:`_forward`'s (read only).
        weights: (R, W - 7) float32 each block's weight.
        c: (8, 8) float32 :func:`_dct_matrix`.
        out: (R + 7, W) float32 the rows the blocks cover (added to).
        acc: (R + 7, W) float32 (added to).
    """
    r, columns = weights.shape
    flat = coeffs.reshape(-1, BLOCK)
    along_columns = (flat @ c).reshape(r, columns, BLOCK, BLOCK)  # [y, x, v, row in block]
    along_columns *= weights[..., None, None]
    placed = np.zeros((r + BLOCK - 1, columns, BLOCK), np.float32)
    for i, block_row in enumerate(np.moveaxis(along_columns, 3, 0)):
        placed[i:i + r] += block_row
    pixels = (placed.reshape(-1, BLOCK) @ c).reshape(r + BLOCK - 1, columns, BLOCK)  # [row, x, column in block]
    for j, block_column in enumerate(np.moveaxis(pixels, 2, 0)):
        out[:, j:j + columns] += block_column
    box = np.zeros((r + BLOCK - 1, columns), np.float32)
    for i in range(BLOCK):
        box[i:i + r] += weights
    for j in range(BLOCK):
        acc[:, j:j + columns] += box


def restore_sums(sums: NDArray[np.float32], frames: NDArray[np.float32], scale: float, wide_px: float,
                 sharpness: float, deblur: float | tuple[float, float] = DEBLUR) -> NDArray[np.float32]:
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
