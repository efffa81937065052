"""Image kernels of the photon budget: block binning, masked correlation, direct binned registration.

One block grid for every binned image in the run: binned pixel ``u`` covers input pixels
``k u .. k u + k - 1`` and is centred on ``k u + (k - 1) / 2`` (with pixel centres at
integers, input ``x`` is binned ``(x + 0.5) / k - 0.5``: :func:`~photonpano.geometry.scale_matrix`).

- :func:`block_mean`: the mean of each k x k block of one image, ignoring untrusted
  pixels (the probe's images, the binned check's frames, the panorama agreement);
- :func:`bin_counts`: the same blocks of a stack of photon-count images, summed or
  averaged without a mask (the binned capture, :class:`~photonpano.budget.grid.BinnedSource`).
  Both give the same block means; they differ in float32 rounding only (OpenCV's area
  resampling against strided sums; measured up to 1e-5 on values up to 37), so each
  keeps its kernel and the results of a run do not change;
- :func:`normalised_correlation`, :func:`phase_shift_correlation`, :func:`binned_frame`,
  :func:`warped_correlation`, :func:`register_binned`, :func:`register_binned_motions`:
  what the probe, the binned check (:class:`~photonpano.schemes.check.PairCheck`) and
  the agreement measure with them (a moving object's pull on them: :mod:`photonpano.movers`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .jit import cached_njit

__all__ = ["block_mean", "bin_counts", "normalised_correlation", "phase_shift_correlation", "binned_frame",
           "warped_correlation", "register_binned", "register_binned_motions", "in_binned_pixels",
           "refine_binned_homography"]


def block_mean(image: NDArray[np.floating], factor: int, mask: NDArray[np.bool_] | None = None
                 ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Average ``factor`` x ``factor`` blocks of an image, ignoring untrusted pixels.

    Args:
        image: (H, W) float image (NaN allowed where ``mask`` is False).
        factor: block size in pixels (>= 1); the image is cropped to a multiple of it.
        mask: (H, W) bool trusted pixels (None: all finite pixels).

    Returns:
        ``(binned, valid)``: (H // factor, W // factor) float32 block means and bool
        blocks with at least 90 % trusted pixels. Binned pixel ``u`` covers input pixels
        ``factor * u .. factor * u + factor - 1``, i.e. its centre is at
        ``factor * u + (factor - 1) / 2``.
    """
    import cv2

    h, w = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    image = image[:h, :w]
    trusted = np.isfinite(image) if mask is None else (mask[:h, :w] & np.isfinite(image))
    values = np.where(trusted, image, 0).astype(np.float32)
    size = (w // factor, h // factor)
    total = cv2.resize(values, size, interpolation=cv2.INTER_AREA)
    weight = cv2.resize(trusted.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    valid = weight >= 0.9
    return np.where(valid, total / np.maximum(weight, 1e-6), 0).astype(np.float32), valid


def normalised_correlation(a: NDArray[np.floating], b: NDArray[np.floating],
                           valid: NDArray[np.bool_]) -> float:
    """Pearson correlation of two images over ``valid`` pixels (0 with fewer than 16).

    Args:
        a: (H, W) image (float32 pairs are read as float32, others as float64).
        b: (H, W) image of the same shape.
        valid: (H, W) bool pixels to compare.

    Returns:
        The correlation in [-1, 1], computed in float64 in two passes (means, then
        centred products), in one compiled loop that releases the GIL: the check of
        every level-1 pair calls this (0.36 ms per 127x248 pair in numpy, mostly
        masked copies held under the GIL).
    """
    dtype = np.result_type(a, b, np.float32)  # float32 pairs stay float32, anything else is float64
    a, b = np.ascontiguousarray(a, dtype=dtype), np.ascontiguousarray(b, dtype=dtype)
    return float(_masked_correlation(a.reshape(-1), b.reshape(-1), np.ascontiguousarray(valid).reshape(-1)))


@cached_njit(nogil=True)
def _masked_correlation(a, b, valid):  # pragma: no cover - compiled
    n, sum_a, sum_b = 0, 0.0, 0.0
    for i in range(a.size):
        if valid[i]:
            n += 1
            sum_a += a[i]
            sum_b += b[i]
    if n < 16:
        return 0.0
    mean_a, mean_b = sum_a / n, sum_b / n
    aa, bb, ab = 0.0, 0.0, 0.0
    for i in range(a.size):
        if valid[i]:
            x, y = a[i] - mean_a, b[i] - mean_b
            aa += x * x
            bb += y * y
            ab += x * y
    denominator = math.sqrt(aa * bb)
    return ab / denominator if denominator > 0 else 0.0


def phase_shift_correlation(a: NDArray[np.float32], b: NDArray[np.float32]
                            ) -> tuple[NDArray[np.float64], float]:
    """Translation of ``b`` relative to ``a`` by phase correlation, and their correlation after it.

    Args:
        a: (H, W) float32 image.
        b: (H, W) float32 image of the same shape.

    Returns:
        ``(shift, correlation)``: (2,) float64 ``(dx, dy)`` in pixels of the images, and
        :func:`normalised_correlation` of ``a`` with ``b`` moved back by it (2-pixel
        border left out).
    """
    import cv2

    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(a - a.mean(), b - b.mean(), window)
    h, w = a.shape
    moved = np.asarray(cv2.warpAffine(b, np.array([[1, 0, -dx], [0, 1, -dy]], np.float32), (w, h),
                                      flags=cv2.INTER_LINEAR, borderValue=np.nan), np.float32)  # no copy
    valid = np.isfinite(moved)
    valid[:2], valid[-2:], valid[:, :2], valid[:, -2:] = False, False, False, False
    return np.array([dx, dy]), normalised_correlation(a, moved, valid)


def bin_counts(counts: NDArray, factor: int, dtype: Any = np.float32, *, mean: bool = True) -> NDArray:
    """Sum (or mean) of each ``factor`` x ``factor`` block of pixels of B count images.

    Args:
        counts: (B, H, W) detection counts (any real dtype).
        factor: block size k in pixels (>= 1).
        dtype: dtype of the result (an integer dtype must hold ``k^2`` times the counts).
        mean: divide by ``k^2`` (the mean count per sensor pixel), else the block sums.

    Returns:
        (B, H // k, W // k) ``dtype`` per block (the last ``H % k`` rows and ``W % k``
        columns are left out).
    """
    b, h, w = counts.shape
    k = int(factor)
    hb, wb = h // k, w // k
    if k == 2 and not mean and counts.dtype.kind == "u" and np.dtype(dtype).kind == "u":
        out = np.empty((b, hb, wb), dtype)  # photon counts binned 2x2 (the default): one compiled pass, 9x faster
        _bin_counts_2x2(np.ascontiguousarray(counts), out)
        return out
    out = np.zeros((b, hb, wb), dtype)
    for dy in range(k):  # k^2 strided adds: several times faster than a sum over a 5-D reshape
        rows = counts[:, dy:hb * k:k]
        for dx in range(k):
            out += rows[:, :, dx:wb * k:k]
    if mean:
        out *= out.dtype.type(1.0 / (k * k))
    return out


@cached_njit(nogil=True)
def _bin_counts_2x2(counts, out):  # pragma: no cover - compiled
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            top, bottom, row = counts[b, 2 * i], counts[b, 2 * i + 1], out[b, i]
            for j in range(row.size):
                row[j] = top[2 * j] + top[2 * j + 1] + bottom[2 * j] + bottom[2 * j + 1]


def in_binned_pixels(homography: NDArray[np.float64], factor: int, *, back: bool = False) -> NDArray[np.float64]:
    """A (3, 3) homography of full-resolution pixels in pixels of blocks of ``factor`` (``back``: the reverse).

    Binned pixel ``u`` is centred on full-resolution ``factor * u + (factor - 1) / 2``
    (:func:`block_mean`), so ``u = (x + 0.5) / factor - 0.5``:
    :func:`~photonpano.geometry.scale_matrix`'s map, as for ``RegistrationGrid``.
    """
    if factor == 1:
        return homography
    s = geometry.scale_matrix(1.0 / factor)
    return np.linalg.inv(s) @ homography @ s if back else s @ homography @ np.linalg.inv(s)


def binned_frame(flux: NDArray[np.float32], mask: NDArray[np.bool_], factor: int, blur: int = 5
                 ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """A merged frame as a binned, blurred square-root flux image for direct registration.

    Args:
        flux: (H, W) float32 flux in photons/s, NaN where unobserved.
        mask: (H, W) bool trusted pixels.
        factor: binning (pixels per side).
        blur: Gaussian filter size in binned pixels (odd; 1 = none).

    Returns:
        ``(image, valid)``: (H // factor, W // factor) float32 and bool (see
        :func:`block_mean`).
    """
    import cv2

    image, valid = block_mean(np.sqrt(np.maximum(flux, 0)), factor, mask)
    if blur > 1:
        image = np.asarray(cv2.GaussianBlur(image, (blur, blur), 0), np.float32)  # float32 already (no copy)
        weight = cv2.GaussianBlur(valid.astype(np.float32), (blur, blur), 0)
        image = np.where(valid, image / np.maximum(weight, 1e-6), 0).astype(np.float32)
    return image, valid


def _warp(image: NDArray[np.float32], valid: NDArray[np.bool_], homography: NDArray[np.float64]):
    """Frame b's binned image in frame a's binned grid: ``out(x) = image(inv(H) x)``."""
    import cv2

    h, w = image.shape
    moved = cv2.warpPerspective(image, homography, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
    inside = cv2.warpPerspective(valid.astype(np.uint8), homography, (w, h), flags=cv2.INTER_NEAREST,
                                 borderValue=0) > 0
    return moved, inside


def warped_correlation(a: tuple[NDArray, NDArray], b: tuple[NDArray, NDArray],
                       homography: NDArray[np.float64], factor: int) -> tuple[float, int]:
    """Correlation of binned frame a with binned frame b warped by ``homography`` (b to a, full pixels).

    Returns:
        ``(correlation, overlap)``: Pearson correlation over the binned pixels valid in
        both, and their number.
    """
    moved, inside = _warp(b[0], b[1], in_binned_pixels(homography, factor))
    both = inside & a[1]
    return normalised_correlation(a[0], moved, both), int(both.sum())


def register_binned(a: tuple[NDArray, NDArray], b: tuple[NDArray, NDArray], initial: NDArray[np.float64],
                    factor: int, *, iterations: int = 50, from_initial: bool = False
                    ) -> tuple[NDArray[np.float64], float, int]:
    """Register two binned frames directly: the better-correlating of :func:`register_binned_motions`.

    An affine correction of the estimate and a translation of its shift alone, which a
    level-1 estimate's own shear or scale (chained from noisy links) cannot hold on smooth
    or noisy frames (the suite's clock 0.362 -> 0.104 px, for a third more CPU per call;
    ``docs/accuracy.md``). Arguments as :func:`register_binned_motions`.

    Returns:
        ``(homography, correlation, overlap)`` of the better one (the affine one on a tie;
        ``initial``, -1, 0 where ECC failed both ways).
    """
    return max(register_binned_motions(a, b, initial, factor, iterations=iterations,
                                       from_initial=from_initial).values(), key=lambda found: found[1])


def register_binned_motions(a: tuple[NDArray, NDArray], b: tuple[NDArray, NDArray], initial: NDArray[np.float64],
                            factor: int, *, iterations: int = 50, from_initial: bool = False
                            ) -> dict[str, tuple[NDArray[np.float64], float, int]]:
    """Register two binned frames directly, twice: phase correlation, then an affine or a translation ECC.

    Each ECC (Evangelidis and Psarakis, 2008) starts from a phase correlation's shift:
    ``"affine"`` corrects b warped by the current estimate (rotation, zoom, perspective),
    ``"translation"`` moves b by the estimate's centre shift alone. The level-1 pair check
    chooses between them per pair, then for the level's rescues together
    (:meth:`~photonpano.schemes.check.LevelCheck.settle`).

    Args:
        a: :func:`binned_frame` of frame a (the moving image).
        b: :func:`binned_frame` of frame b (the template).
        initial: (3, 3) float64 current estimate mapping b's full-resolution pixels to a's.
        factor: the frames' binning.
        iterations: ECC iterations.
        from_initial: run each ECC from its base warp too (the estimate, or its shift):
            phase correlation follows the edges of masked-out regions, which move with them.

    Returns:
        ``{"affine": r, "translation": r}``, each ``r`` ``(homography, correlation,
        overlap)``: (3, 3) float64 mapping b's full-resolution pixels to a's, the final
        correlation and the binned pixels compared (``initial``, -1, 0 where its ECC failed).
    """
    import cv2

    start = in_binned_pixels(initial, factor)
    centre = (np.array([b[0].shape[::-1]], np.float64) - 1) / 2  # (1, 2): x, y
    shifted = geometry.translation(*(geometry.apply(start, centre)[0] - centre[0]))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-5)
    window = cv2.createHanningWindow(b[0].shape[::-1], cv2.CV_32F)
    fill_a = np.where(a[1], a[0], a[0][a[1]].mean() if a[1].any() else 0).astype(np.float32)
    found_by: dict[str, tuple[NDArray[np.float64], float, int]] = {}
    for base, motion, name in ((start, cv2.MOTION_AFFINE, "affine"), (shifted, cv2.MOTION_TRANSLATION, "translation")):
        best = found_by[name] = (initial, -1.0, 0)
        moved, inside = _warp(b[0], b[1], base)
        fill_b = np.where(inside, moved, moved[inside].mean() if inside.any() else 0).astype(np.float32)
        (dx, dy), _ = cv2.phaseCorrelate(fill_a - fill_a.mean(), fill_b - fill_b.mean(), window)
        # moved(x) ~ a(x - d): the correction maps moved's pixels to a's by x - d
        starts = [np.array([[1, 0, -dx], [0, 1, -dy]], np.float32)] + [np.eye(2, 3, dtype=np.float32)] * from_initial
        for warp in starts:
            found = _ecc_correction(a, moved, inside, base, warp, motion, criteria, factor)
            if found is not None and found[1] > best[1]:
                best = found_by[name] = found
    return found_by


def _ecc_correction(a: tuple[NDArray, NDArray], moved: NDArray[np.float32], inside: NDArray[np.bool_],
                    base: NDArray[np.float64], warp: NDArray[np.float32], motion: int, criteria: tuple,
                    factor: int) -> tuple[NDArray[np.float64], float, int] | None:
    """One OpenCV ECC of binned frame b warped by ``base`` (``moved``, valid ``inside``) to frame a.

    Args:
        a: :func:`binned_frame` of frame a (the template of the correction).
        moved: (h, w) float32 binned frame b warped by ``base``.
        inside: (h, w) bool its valid pixels.
        base: (3, 3) float64 the warp ``moved`` was made with, in binned pixels.
        warp: (2, 3) or (3, 3) float32 starting correction (3 x 3 for ``MOTION_HOMOGRAPHY``).
        motion: OpenCV's ``MOTION_*`` model.
        criteria: OpenCV's termination criteria.
        factor: the frames' binning.

    Returns:
        ``(homography, correlation, overlap)``: (3, 3) float64 ``correction @ base`` mapping
        b's full-resolution pixels to a's, the final correlation and the binned pixels
        compared; None where ECC failed.
    """
    import cv2

    try:
        cc, refined = cv2.findTransformECCWithMask(moved, a[0], inside.astype(np.uint8), a[1].astype(np.uint8), warp,
                                                   motion, criteria, 1)
    except cv2.error:
        return None
    correction = np.eye(3)
    correction[:len(refined)] = refined
    found = geometry.normalize(in_binned_pixels(correction @ base, factor, back=True))
    return found, float(cc), int((inside & a[1]).sum())


def refine_binned_homography(a: tuple[NDArray, NDArray], b: tuple[NDArray, NDArray], homography: NDArray[np.float64],
                             factor: int, *, iterations: int = 30) -> tuple[NDArray[np.float64], float, int]:
    """Refine a registration of two binned frames by a homography ECC: its perspective too.

    b warped by ``homography`` is registered to a by OpenCV's ECC with the full eight
    parameters, from the identity. The pair check refines each rescue's affine
    registration so (:meth:`~photonpano.schemes.check.LevelCheck.settle` decides whether
    the level keeps the perspective). Arguments as :func:`register_binned_motions`.

    Returns:
        ``(homography, correlation, overlap)``: (3, 3) float64 mapping b's full-resolution
        pixels to a's, the final correlation and the binned pixels compared
        (``homography``, -1, 0 where ECC failed).
    """
    import cv2

    base = in_binned_pixels(homography, factor)
    moved, inside = _warp(b[0], b[1], base)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-5)
    found = _ecc_correction(a, moved, inside, base, np.eye(3, dtype=np.float32), cv2.MOTION_HOMOGRAPHY, criteria,
                            factor)
    return (homography, -1.0, 0) if found is None else found
