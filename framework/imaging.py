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
  :func:`warped_correlation`, :func:`register_binned`: what the probe, the binned check
  (:class:`~photonpano.schemes.check.PairCheck`) and the agreement measure with them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .jit import cached_njit

__all__ = ["block_mean", "bin_counts", "normalised_correlation", "phase_shift_correlation", "binned_frame",
           "warped_correlation", "register_binned", "in_binned_pixels", "brightest_blob", "shift_without_mover"]


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
    """Register two binned frames directly: phase correlation, then ECC, affine and translation.

    Of two ECC registrations (Evangelidis and Psarakis, 2008), each from a phase
    correlation's shift, the better-correlating is returned: an *affine* correction of b
    warped by the current estimate (rotation, zoom, perspective), and a *translation* of b
    moved by the estimate's centre shift alone, which a level-1 estimate's own shear or
    scale (chained from noisy links) cannot hold on smooth or noisy frames (the suite's
    clock 0.362 -> 0.104 px, for a third more CPU per call; ``docs/accuracy.md``).

    Args:
        a: :func:`binned_frame` of frame a (the moving image).
        b: :func:`binned_frame` of frame b (the template).
        initial: (3, 3) float64 current estimate mapping b's full-resolution pixels to a's.
        factor: the frames' binning.
        iterations: ECC iterations.
        from_initial: run each ECC from its base warp too (the estimate, or its shift):
            phase correlation follows the edges of masked-out regions, which move with them.

    Returns:
        ``(homography, correlation, overlap)``: (3, 3) float64 mapping b's full-resolution
        pixels to a's, the final correlation and the binned pixels compared (``initial``,
        -1, 0 where ECC failed both ways).
    """
    import cv2

    start = in_binned_pixels(initial, factor)
    centre = (np.array([b[0].shape[::-1]], np.float64) - 1) / 2  # (1, 2): x, y
    shifted = geometry.translation(*(geometry.apply(start, centre)[0] - centre[0]))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-5)
    window = cv2.createHanningWindow(b[0].shape[::-1], cv2.CV_32F)
    fill_a = np.where(a[1], a[0], a[0][a[1]].mean() if a[1].any() else 0).astype(np.float32)
    best: tuple[NDArray[np.float64], float, int] = (initial, -1.0, 0)
    for base, motion in ((start, cv2.MOTION_AFFINE), (shifted, cv2.MOTION_TRANSLATION)):
        moved, inside = _warp(b[0], b[1], base)
        fill_b = np.where(inside, moved, moved[inside].mean() if inside.any() else 0).astype(np.float32)
        (dx, dy), _ = cv2.phaseCorrelate(fill_a - fill_a.mean(), fill_b - fill_b.mean(), window)
        # moved(x) ~ a(x - d): the correction maps moved's pixels to a's by x - d
        starts = [np.array([[1, 0, -dx], [0, 1, -dy]], np.float32)] + [np.eye(2, 3, dtype=np.float32)] * from_initial
        for warp in starts:
            try:
                cc, refined = cv2.findTransformECCWithMask(moved, a[0], inside.astype(np.uint8),
                                                           a[1].astype(np.uint8), warp, motion, criteria, 1)
            except cv2.error:
                continue
            if cc > best[1]:
                correction = np.vstack([refined.astype(np.float64), [0, 0, 1]])
                found = geometry.normalize(in_binned_pixels(correction @ base, factor, back=True))
                best = (found, float(cc), int((inside & a[1]).sum()))
    return best


def brightest_blob(image: NDArray[np.float32], valid: NDArray[np.bool_], *,
                   levels: tuple[float, ...] = (0.25, 0.5, 0.75), margin: int = 3, grow: int = 6,
                   max_fraction: float = 0.25, min_solidity: float = 0.5, min_share: float = 0.9
                   ) -> NDArray[np.bool_]:
    """The bright compact region that carries most of a binned frame's contrast, if there is one.

    A single bright, compact region (a lit object crossing a dark scene) can carry most of
    a binned frame's contrast, so a correlation, phase correlation or ECC of two frames
    then follows that region's motion, which is the scene's only if the region is static.
    The pair check registers and checks the frames again without it
    (:class:`~photonpano.schemes.check.PairCheck`).

    On a bright, textured scene the object touches the scene's own bright texture (a lit
    disc on a brick facade's mortar lines, half as bright as it): above the first level
    they form one web, neither small nor compact. The higher ``levels`` then cut the
    object's core out of the web; such a core counts only where it holds at least
    ``min_share`` of the contrast energy above its level (a static scene's brightest
    patch of texture has rivals there, the object none), and it is grown back into the
    pixels above the first level within ``grow`` pixels (its motion-blurred ends). On the
    brick facade crossed by a disc of radius 30 px (level 1's merged frames, 2026-11-26)
    the first level found the disc in 7 of the 27 frames that show it, the three levels
    in all 27, and in none of the 63 frames of the static capture.

    Args:
        image: (h, w) float32 binned frame (:func:`binned_frame`).
        valid: (h, w) bool its valid pixels.
        levels: increasing fractions (each in (0, 1)); at each in turn the candidate
            regions are where the image exceeds its median by that fraction of the
            brightest valid pixel's excess.
        margin: dilation of the region in binned pixels (the blurred rim).
        grow: binned pixels by which a core found at a higher level grows into the
            pixels above the first level.
        max_fraction: a region over this fraction of the valid pixels (dilated) is no
            compact object (a bright sky).
        min_solidity: nor is a region covering less than this fraction of its convex hull
            (a web of bright texture or noise over a bright, plain scene).
        min_share: the energy share a region found above a higher level must hold.

    Returns:
        (h, w) bool: at the first level that gives one, the 8-connected candidate region
        with the largest summed squared excess that is small and compact enough (and at
        the higher levels holds ``min_share``), grown and dilated; all False where no
        valid pixel exceeds the median or no level gives such a region.
    """
    import cv2

    none = np.zeros(image.shape, bool)
    if not valid.any():
        return none
    excess = np.where(valid, image - np.median(image[valid]), 0).astype(np.float32)
    peak = float(excess.max())
    if not peak > 0:
        return none
    for k, level in enumerate(levels):
        count, labels = cv2.connectedComponents((excess > level * peak).astype(np.uint8), connectivity=8)
        energy = np.bincount(labels.ravel(), weights=(excess * excess).ravel(), minlength=count)
        energy[0] = 0  # the background label
        blob = labels == int(np.argmax(energy))
        if k and energy.max() < min_share * energy.sum():
            continue
        hull = cv2.convexHull(np.argwhere(blob)[:, ::-1].astype(np.int32))
        if blob.sum() < min_solidity * cv2.contourArea(hull):
            continue
        if k:
            near = cv2.dilate(blob.astype(np.uint8), np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)) > 0
            blob |= near & (excess > levels[0] * peak)
        blob = cv2.dilate(blob.astype(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)) > 0
        if blob.sum() <= max_fraction * valid.sum():
            return blob
    return none


MOVER_DISAGREEMENT_PX = 0.5
"""Binned pixels by which a probe's shift without the brightest blob must differ from its
whole frames' shift to replace it (:func:`shift_without_mover`)."""

MOVER_MIN_CORRELATION = 0.8
"""Correlation the registration without the brightest blob must reach to replace a probe's
shift (:func:`shift_without_mover`): photon noise alone keeps a dark capture's below it."""


def shift_without_mover(a: NDArray[np.float32], b: NDArray[np.float32], shift: NDArray[np.float64],
                        correlation: float, min_correlation: float) -> tuple[NDArray[np.float64], float]:
    """The shift of two binned blocks, checked against a moving object's pull.

    The speed probe of :func:`~photonpano.budget.probe.probe_capture` uses it. Phase
    correlation whitens the spectrum, so the sharp rim of a bright object crossing a
    smooth scene can carry it to the object's motion; the 75th percentile of the probes'
    speeds then sizes the groups for that motion (objects_coffee crossed by a disc of
    radius 30 px at 0.08 px/frame: 0.041 px/frame probed, 0.027 without the disc: groups
    of 240 frames instead of 370, and 0.27 px RMSE instead of 0.16 with the static plan).
    The blocks are registered again by ECC (:func:`register_binned`, which weighs
    every pixel's contrast), without each block's :func:`brightest_blob`; the shift of
    the image centre found so replaces the phase correlation's where it correlates at
    :data:`MOVER_MIN_CORRELATION` or more and differs by more than
    :data:`MOVER_DISAGREEMENT_PX` in length (what it changed on the evaluation suite:
    ``docs/real_scenes.md``, "The speed probe").

    Args:
        a: (h, w) float32 binned sum of the first of two adjacent blocks.
        b: (h, w) float32 the same of the second.
        shift: (2,) float64 ``(dx, dy)`` of ``b`` relative to ``a`` by phase correlation,
            in binned pixels.
        correlation: the phase correlation's correlation after the shift.
        min_correlation: the probe's correlation limit.

    Returns:
        ``(shift, correlation)``: the shift and correlation to use.
    """
    valid = np.isfinite(a) & np.isfinite(b)
    blob_a, blob_b = brightest_blob(a, valid), brightest_blob(b, valid)
    h, cc, _ = register_binned((a, valid & ~blob_a), (b, valid & ~blob_b), np.eye(3), 1, from_initial=True)
    centre = np.array([(a.shape[1] - 1) / 2, (a.shape[0] - 1) / 2])
    moved = geometry.apply(h, centre[None])[0] - centre  # b's centre in a's pixels
    agree = abs(float(np.hypot(*moved)) - float(np.hypot(*shift))) <= MOVER_DISAGREEMENT_PX
    if cc < max(min_correlation, MOVER_MIN_CORRELATION) or agree:
        return shift, correlation
    return moved, float(cc)
