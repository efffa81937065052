"""Robust merge: leave out the observations of a canvas pixel that disagree with the static scene.

A panorama merges every binary frame; an object moving across the scene leaves a faint
streak along its path (its photons are merged with the background's at every canvas
pixel it crossed). A robust compositor keeps one pair of sums (detections S, frames N)
per *virtual exposure*: the capture cut into ``exposures`` equal runs of consecutive
frames, or, where a lamp flickers (:meth:`~photonpano.stages.Compositor.expect_flicker`),
into runs of the same whole number of flicker periods (:func:`exposure_bounds`), so that
each run sees the lamp's mean level. At :meth:`~photonpano.stages.Compositor.finish`,
:func:`robust_combine` compares each exposure's estimate of each canvas pixel with the static scene, the
frame-weighted median over the exposures, and leaves out the exposures that disagree:
the median-of-exposures test with the robustness term of burst merging (Hasinoff et al.,
"Burst photography for high dynamic range and low-light imaging on mobile cameras",
SIGGRAPH Asia 2016, Sec. 5; Wronski et al., "Handheld multi-frame super-resolution",
SIGGRAPH 2019, Sec. 5: a pixel's sample is down-weighted where it differs from the
reference by more than the noise explains). The test, per exposure k and canvas pixel:

- ``S_k`` and ``N_k`` are smoothed by a Gaussian of ``smooth_px`` frame pixels
  (normalised convolution), and turned into flux ``phi_k`` (paper Eq. (3) without the
  exposure time: ``-ln(1 - S_k / N_k)``; the mean for intensity sources);
- ``phi`` is the median of the ``phi_k`` weighted by ``N_k``; each exposure's global
  gain (median of ``phi_k / phi``, a lamp over the whole scene) is divided out;
- exposure k disagrees where ``|phi_k - phi|`` exceeds ``sigmas`` times its noise
  (binomial: ``p / ((1 - p) N_k A)`` with ``A`` the Gaussian's effective area, or the
  spread of the exposures, 1.4826 x their weighted median absolute deviation, whichever is
  larger) *and* ``tolerance`` times ``phi`` (:data:`TOLERANCE`); under a flickering lamp,
  an exposure that saw the pixel for only part of its periods is not tested there
  (:func:`partly_seen`);
- a morphological opening by a disc ``min_width_px`` wide of the pixels where any exposure
  disagrees drops thin disagreements (a slightly misregistered edge) and points, and a
  dilation by ``margin_px`` takes the object's blurred rim; each exposure is left out
  where it disagrees (dilated alike) inside what the opening keeps.

The panorama is then the flux of the sums over the exposures left, and the canvas
pixels where any exposure was left out are the moving-object mask (``moving.png``).
What moves for more than half the frames that see a pixel is the static scene there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["DEFAULT_EXPOSURES", "TOLERANCE", "exposure_bounds", "exposure_index", "feed_exposures",
           "join_exposures", "fed_ranges", "left_out_in_frames", "partly_seen", "whole_period_frames",
           "robust_combine", "robust_rejection", "keep_exposures"]

TOLERANCE = 0.1
"""Smallest relative flux difference from the static scene that leaves an exposure out.

Chosen on the true-motion merges of a disc (radius 30 px, 0.08 px/frame) crossing seven
photographs: 0.25 left a faint ghost where the disc is within a quarter of the background
(the clock 1.5 dB, the astronaut 0.5 dB under the static capture's merge), 0.1 leaves at
most 0.18 dB (the clock); the static captures lose at most 0.04 dB (the Hubble field)."""

DEFAULT_EXPOSURES = 16
"""Virtual exposures a robust compositor keeps apart (20 000 frames: 1 250 frames each;
a disc of radius 30 px at 0.08 px/frame covers a canvas pixel for 750 frames)."""


def exposure_bounds(total_frames: int, exposures: int, frame_step: int = 1,
                    period_frames: float | None = None) -> NDArray[np.int64]:
    """Where each virtual exposure begins, then the frame count: the robust merge's runs of frames.

    Without a flicker period, ``exposures`` equal runs: exposure k begins at
    ``ceil(k T / exposures)``. With one (a lamp flickering over part of the scene,
    :meth:`photonpano.flicker.Flicker.period_frames`), every run spans the same whole number
    of periods, ``q = max(1, floor(T / (exposures P)))``, so that each averages the lamp
    alike: ``floor(T / (q P))`` runs beginning at ``round(k q P)`` (up to twice
    ``exposures``), the last one also taking the frames left over.

    Args:
        total_frames: frames T of the capture.
        exposures: number of virtual exposures asked for (>= 1).
        frame_step: beginnings are rounded up to multiples of this (sources counted in blocks).
        period_frames: flicker period P in binary frames, or None.

    Returns:
        (E + 1,) int64 strictly increasing: 0, the E - 1 inner beginnings in ``(0, T)``, T.
    """
    total = int(total_frames)
    if period_frames is not None and period_frames > 0:
        length = max(1, int(total / (max(1, int(exposures)) * period_frames) + 1e-6)) * float(period_frames)
        at = np.round(np.arange(1, max(1, int(total / length + 1e-6))) * length).astype(np.int64)
    else:
        k = np.arange(1, max(1, int(exposures)), dtype=np.int64)
        at = -(-(k * total) // max(1, int(exposures)))
    step = max(1, int(frame_step))
    at = -(-at // step) * step
    return np.concatenate([[0], np.unique(at[(at > 0) & (at < total)]), [total]]).astype(np.int64)


def exposure_index(edges: NDArray[np.int64], bounds: NDArray[np.int64]) -> NDArray[np.int64]:
    """The virtual exposure of each frame range: the one its middle frame falls in.

    Args:
        edges: (B + 1,) int64 frame-range edges (range b is ``edges[b]:edges[b + 1]``).
        bounds: (E + 1,) int64 :func:`exposure_bounds`.

    Returns:
        (B,) int64 exposure indices in ``[0, E)``.
    """
    edges = np.asarray(edges, np.int64)
    middle = (edges[:-1] + edges[1:] - 1) // 2
    return np.clip(np.searchsorted(bounds, middle, side="right") - 1, 0, len(bounds) - 2)


def feed_exposures(accs: list[Any], new: Callable[[], Any], add: Callable[..., None], edges: NDArray[np.int64],
                   counts: NDArray, homographies: NDArray[np.float64], bounds: NDArray[np.int64]) -> None:
    """Add a compositor's sub-batch to the accumulators of the virtual exposures its ranges fall in.

    Args:
        accs: one accumulator per exposure (``len(bounds) - 1``), None until first fed;
            filled in place with ``new()``.
        new: makes an empty accumulator.
        add: ``add(acc, counts, n_frames, homographies)`` adds a sub-batch to ``acc``.
        edges: (B + 1,) int64 frame-range edges of the sub-batch's B ranges.
        counts: (B, H, W) counts of the ranges.
        homographies: (B, 3, 3) float64 frame-to-canvas homographies of the ranges.
        bounds: (E + 1,) int64 :func:`exposure_bounds` of the capture.
    """
    edges = np.asarray(edges, np.int64)
    which = exposure_index(edges, bounds)
    for k in np.unique(which):
        if accs[k] is None:
            accs[k] = new()
        pick = which == k
        add(accs[k], counts[pick], np.diff(edges)[pick], homographies[pick])


def whole_period_frames(bounds: NDArray[np.int64], accs: list[Any],
                        period_frames: float | None) -> NDArray[np.int64] | None:
    """The ``exposure_frames`` of :func:`robust_rejection` for a compositor's exposures fed so far.

    Args:
        bounds: (E + 1,) int64 :func:`exposure_bounds` of the capture.
        accs: the E accumulators, None where an exposure got no frames.
        period_frames: the flicker period the bounds span whole periods of, or None.

    Returns:
        (K',) int64 binary frames of each exposure fed (K' of E, in order); None without a period.
    """
    if period_frames is None:
        return None
    return np.diff(bounds)[[k for k, acc in enumerate(accs) if acc is not None]]


def fed_ranges(bounds: NDArray[np.int64], accs: list[Any]) -> NDArray[np.int64]:
    """(K', 2) int64 first binary frame and end of each exposure fed (K' of the E ``accs``, in order).

    Args:
        bounds: (E + 1,) int64 :func:`exposure_bounds` of the capture.
        accs: the E accumulators, None where an exposure got no frames.
    """
    fed = np.array([k for k, acc in enumerate(accs) if acc is not None], np.int64)
    return np.stack([bounds[fed], bounds[fed + 1]], axis=1).astype(np.int64).reshape(-1, 2)


def left_out_in_frames(rejected: NDArray[np.bool_], ranges: NDArray[np.int64], start: NDArray[np.int64],
                       stop: NDArray[np.int64], to_canvas: NDArray[np.float64], shape: tuple[int, int],
                       margin_px: int = 3) -> NDArray[np.bool_]:
    """Where a robust merge left out the exposures of each group's frames, in the group's frame grid.

    An exposure is left out where a mover was during its frames, so the exposures that
    overlap a group's frames say where the mover was while the group was taken, even where
    it barely stands out of the group's merged frame (a bright disc over a sun's glow):
    the mosaic levels leave those pixels out of the group's registration
    (:mod:`photonpano.schemes.mosaic`).

    Args:
        rejected: (K, Hc, Wc) bool exposures left out per canvas pixel (:attr:`photonpano.records.Panorama.rejected`).
        ranges: (K, 2) int64 first binary frame and end of each exposure (:func:`fed_ranges`).
        start: (G,) int64 first binary frame of each group.
        stop: (G,) int64 end (exclusive) of each group.
        to_canvas: (G, 3, 3) float64 each group's frame pixels to canvas pixels.
        shape: ``(H, W)`` of the frame grid.
        margin_px: dilation of what is left out, in frame pixels.

    Returns:
        (G, H, W) bool, True where group g's frames fall in an exposure left out there.
    """
    import cv2

    h, w = shape
    out = np.zeros((len(start), h, w), bool)
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    for g in range(len(start)):
        overlapping = (ranges[:, 0] < stop[g]) & (ranges[:, 1] > start[g])
        canvas = rejected[overlapping].any(axis=0)
        if canvas.any():
            frame = cv2.warpPerspective(canvas.astype(np.uint8), to_canvas[g], (w, h),
                                        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
            out[g] = cv2.dilate(frame, kernel) > 0
    return out


def join_exposures(mine: list[Any], theirs: list[Any], add: Callable[[Any, Any], None]) -> None:
    """Add a compositor fork's per-exposure sums into ``mine`` (in place).

    Args:
        mine: one accumulator per exposure, None where the exposure got no frames.
        theirs: the fork's, alike.
        add: ``add(a, b)`` adds accumulator ``b`` into ``a`` in place.
    """
    for k, other in enumerate(theirs):
        if mine[k] is None:
            mine[k] = other
        elif other is not None:
            add(mine[k], other)


def _weighted_median(values: NDArray[np.float32], weights: NDArray[np.float32]) -> NDArray[np.float32]:
    """Median along axis 0 of ``values`` (K, H, W) weighted by ``weights`` (>= 0; NaN values weigh 0).

    The first value, in ascending order, at which the cumulative weight reaches half the
    total; NaN where no value has weight.
    """
    from ._robust_merge_compiled import weighted_median_kernel  # numba: not at registration

    out = np.empty(values.shape[1:], np.float32)
    weighted_median_kernel(np.ascontiguousarray(values, np.float32), np.ascontiguousarray(weights, np.float32), out)
    return out


def robust_combine(sums: NDArray[np.float32], frames: NDArray[np.float32], *, binary: bool = True, scale: float = 1.0,
                   exposure_frames: NDArray[np.int64] | None = None,
                   **test: float) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Sum the virtual exposures of a canvas, leaving out those that disagree with the static scene.

    :func:`robust_rejection` then :func:`keep_exposures`; see the module docstring for the test.

    Args:
        sums: (K, Hc, Wc) float32 detections (or intensity sums) per exposure and canvas pixel.
        frames: (K, Hc, Wc) float32 binary frames behind them (kernel-weighted).
        binary: photon counts (binomial noise, flux ``-ln(1 - p)``); False: intensity sums.
        scale: canvas pixels per frame pixel.
        exposure_frames: (K,) binary frames in each exposure where they span whole
            flicker periods, else None (:func:`robust_rejection`).
        **test: :func:`robust_rejection`'s ``sigmas``, ``tolerance``, ``smooth_px``,
            ``min_width_px``, ``margin_px``.

    Returns:
        ``(sums, frames, moving)``: (Hc, Wc) float32 sums and frames over the exposures
        kept, and (Hc, Wc) bool, True where an exposure was left out.

    Raises:
        ValueError: if ``sums`` and ``frames`` differ in shape or are not (K, Hc, Wc).
    """
    sums, frames = np.asarray(sums, np.float32), np.asarray(frames, np.float32)
    rejected = robust_rejection(sums, frames, binary=binary, scale=scale, exposure_frames=exposure_frames, **test)
    return keep_exposures(sums, frames, rejected)


def keep_exposures(sums: NDArray[np.float32], frames: NDArray[np.float32], rejected: NDArray[np.bool_]
                   ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Sum the virtual exposures of a canvas over those not ``rejected`` at each pixel.

    Where every exposure that saw a pixel is rejected, all are kept (nothing else is known
    there).

    Args:
        sums: (K, Hc, Wc) float32 detections (or intensity sums) per exposure.
        frames: (K, Hc, Wc) float32 frames behind them.
        rejected: (K, Hc, Wc) bool exposures left out (:func:`robust_rejection`).

    Returns:
        ``(sums, frames, moving)`` as :func:`robust_combine`'s.
    """
    kept_s = np.where(rejected, 0, sums).sum(0)
    kept_n = np.where(rejected, 0, frames).sum(0)
    empty = (kept_n <= 0) & (frames.sum(0) > 0)  # every exposure left out: keep them all
    kept_s = np.where(empty, sums.sum(0), kept_s).astype(np.float32)
    kept_n = np.where(empty, frames.sum(0), kept_n).astype(np.float32)
    return kept_s, kept_n, rejected.any(axis=0) & ~empty


def partly_seen(frames: NDArray[np.float32], exposure_frames: NDArray[np.int64], whole: float = 0.98
                ) -> NDArray[np.bool_]:
    """Which exposures of whole flicker periods saw each canvas pixel for only part of their frames.

    Such an exposure (the pixel came into or left the view during it) averaged the lamp
    over part of a period there: up to the lamp's depth (90 % for a bare mains lamp) away
    from the others, which the robust merge's test would read as a mover. Kept in the
    merge, it weighs in by the few frames it has.

    Args:
        frames: (K, Hc, Wc) float32 binary frames per exposure and canvas pixel
            (kernel-weighted; smoothed, as :func:`robust_rejection` does, where point drops
            leave canvas pixels without a frame's drop).
        exposure_frames: (K,) binary frames in each exposure (:func:`exposure_bounds`
            with a flicker period).
        whole: share of the frames (per frame of the exposure, against the pixel's
            best-seen exposure) below which an exposure is partly seen.

    Returns:
        (K, Hc, Wc) bool.
    """
    per_frame = frames / np.asarray(exposure_frames, np.float32)[:, None, None]
    return (frames > 0) & (per_frame < whole * per_frame.max(axis=0)[None])


def robust_rejection(sums: NDArray[np.float32], frames: NDArray[np.float32], *, binary: bool = True,
                     scale: float = 1.0, sigmas: float = 5.0, tolerance: float | None = None, smooth_px: float = 2.0,
                     min_width_px: float = 9.0, margin_px: float = 3.0,
                     exposure_frames: NDArray[np.int64] | None = None) -> NDArray[np.bool_]:
    """Which virtual exposures disagree with the static scene at each canvas pixel (see the module's test).

    Args:
        sums: (K, Hc, Wc) float32 detections (or intensity sums) per exposure and canvas pixel.
        frames: (K, Hc, Wc) float32 binary frames behind them (kernel-weighted).
        binary: photon counts (binomial noise, flux ``-ln(1 - p)``); False: intensity sums.
        scale: canvas pixels per frame pixel (the lengths below are in frame pixels).
        sigmas: noise threshold in standard deviations.
        tolerance: smallest relative flux difference that counts as disagreement; None:
            :data:`TOLERANCE` (read at each call).
        smooth_px: Gaussian sigma of the smoothing, in frame pixels.
        min_width_px: narrowest disagreeing region left out, in frame pixels.
        margin_px: dilation of the left-out regions, in frame pixels.
        exposure_frames: (K,) binary frames in each exposure where they span whole
            periods of a flickering lamp (:func:`exposure_bounds` with a period), else None.
            The exposures :func:`partly_seen` at a pixel are not tested there.

    Returns:
        (K, Hc, Wc) bool, True where exposure k is left out (none with fewer than 3
        exposures: no majority to speak of).

    Raises:
        ValueError: if ``sums`` and ``frames`` differ in shape or are not (K, Hc, Wc).
    """
    import cv2

    sums, frames = np.asarray(sums, np.float32), np.asarray(frames, np.float32)
    if sums.shape != frames.shape or sums.ndim != 3:
        raise ValueError(f"robust_combine: sums {sums.shape} and frames {frames.shape} must both be (K, Hc, Wc)")
    if len(sums) < 3:  # no majority to speak of
        return np.zeros(sums.shape, bool)
    sigma = smooth_px * scale
    smooth_s = np.stack([cv2.GaussianBlur(s, (0, 0), sigma) for s in sums])
    smooth_n = np.stack([cv2.GaussianBlur(n, (0, 0), sigma) for n in frames])
    seen = smooth_n >= 1.0  # at least one frame's worth behind the smoothed estimate
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(seen, smooth_s / smooth_n, np.nan)
        if binary:
            p = np.clip(p, 0, 1 - 1e-6)
            phi = -np.log1p(-p)
        else:
            phi = p
    phi = phi.astype(np.float32)
    static = _weighted_median(phi, smooth_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(len(phi)):  # each exposure's global gain (a lamp over the whole scene)
            ratio = phi[k] / static
            ok = np.isfinite(ratio) & (static > 0)
            if np.count_nonzero(ok) >= 100:
                phi[k] /= max(float(np.median(ratio[ok])), 1e-6)
    static = _weighted_median(phi, smooth_n)
    deviation = np.abs(phi - static[None])
    spread = 1.4826 * _weighted_median(deviation, smooth_n)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if binary:
            area = 4 * np.pi * sigma * sigma / max(scale * scale, 1.0)  # independent frame pixels averaged
            p_static = -np.expm1(-static)
            noise = np.sqrt(p_static / np.maximum(1 - p_static, 1e-6) / (smooth_n * area))
        else:
            noise = np.zeros_like(phi)
        noise = np.maximum(noise, spread[None])
        least = TOLERANCE if tolerance is None else tolerance
        out = seen & (deviation > sigmas * noise) & (deviation > least * static[None])
        if exposure_frames is not None:
            out &= ~partly_seen(smooth_n, exposure_frames)
    out = out.astype(np.uint8)
    width = max(3, int(round(min_width_px * scale)) | 1)
    opening = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (width, width))
    margin = max(0, int(round(margin_px * scale)))
    grow = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    # the width test on the union over the exposures: a slow mover disagrees in each exposure only in a thin
    # crescent (its leading and trailing edges), which an opening per exposure would drop
    wide = cv2.dilate(cv2.morphologyEx(out.max(axis=0), cv2.MORPH_OPEN, opening), grow) > 0
    rejected = np.zeros(sums.shape, bool)
    for k in range(len(out)):
        if out[k].any():
            rejected[k] = (cv2.dilate(out[k], grow) > 0) & wide
    return rejected
