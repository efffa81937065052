"""Warping binary frames onto a target grid, a sub-batch of frames at a time.

Consecutive binary frames move by a tiny fraction of a pixel (e.g. 0.02 px at 100 kHz),
so frames whose warps differ by well under a pixel are summed first and warped once with
the warp of their middle frame. This keeps the cost at one warp per sub-batch instead of
one per binary frame, with a displacement error bounded by the tolerance.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from . import geometry
from .jit import cached_njit

__all__ = ["subbatch_edges", "WarpAccumulator", "merge_groups"]


def subbatch_edges(homographies: NDArray[np.float64], width: int, height: int,
                   tolerance_px: float, breaks: NDArray[np.int64] | None = None, *, frame_step: int = 1,
                   first_frame: int = 0) -> NDArray[np.int64]:
    """Split consecutive frames into sub-batches whose warps differ by < ``tolerance_px``.

    The split follows the path length of the warped frame corners: a sub-batch ends
    before the corners have travelled ``tolerance_px`` pixels since its first frame, so
    every frame of a sub-batch lies within ``tolerance_px / 2`` of the middle frame.

    Args:
        homographies: (K, 3, 3) float64 warps of K consecutive frames onto the target.
        width: frame width in pixels.
        height: frame height in pixels.
        tolerance_px: largest corner travel within one sub-batch, in target pixels (> 0).
        breaks: frame indices in ``0..K`` where a sub-batch must end (e.g. group
            boundaries, so that the sub-batches of several overlapping groups are shared).
        frame_step: other edges fall on capture frames that are multiples of this (a
            source whose photons are counted in blocks of frames, see
            :class:`photonpano.budget.grid.BinnedBlocks`); a sub-batch then ends at the first
            such frame after its corners travelled ``tolerance_px``.
        first_frame: capture frame index of the first of the K frames.

    Returns:
        (B + 1,) int64 edges into ``0..K`` (``edges[0] == 0``, ``edges[-1] == K``),
        including every break.

    Raises:
        ValueError: if ``tolerance_px`` is not positive.
    """
    if tolerance_px <= 0:
        raise ValueError(f"tolerance_px must be > 0, got {tolerance_px}")
    k = len(homographies)
    if k == 0:
        return np.zeros(1, dtype=np.int64)
    pts = geometry.apply(homographies, geometry.corners(width, height))  # (K, 4, 2)
    step = np.linalg.norm(np.diff(pts, axis=0), axis=-1).max(axis=-1)  # (K-1,)
    forced = np.zeros(k + 1, dtype=bool)
    if breaks is not None:
        forced[np.clip(np.asarray(breaks, dtype=np.int64), 0, k)] = True
    edges = np.empty(k + 1, dtype=np.int64)
    used = _travel_edges(step, forced, float(tolerance_px), int(first_frame), int(frame_step), edges)
    return edges[:used]


@cached_njit(nogil=True)
def _travel_edges(step, forced, tolerance_px, first_frame, frame_step, edges):  # pragma: no cover - compiled
    # a scan with resets, one scalar step per frame: compiled, it does not hold the GIL
    # (every merge and panorama runs it, on the executor's threads)
    edges[0] = 0
    used, travelled = 1, 0.0
    for i in range(1, len(step) + 1):
        travelled += step[i - 1]
        if forced[i] or (travelled >= tolerance_px and (first_frame + i) % frame_step == 0):
            edges[used] = i
            used += 1
            travelled = 0.0
    edges[used] = len(step) + 1
    return used + 1


_IDENTITY = np.eye(3)
_IDENTITY_WARP, _AFFINE_WARP, _PERSPECTIVE_WARP = 0, 1, 2


@cached_njit(nogil=True)
def _footprints(hs, width, height, target_width, target_height, same_grid, boxes, kinds):  # pragma: no cover
    # Per warp of WarpAccumulator.add_many, compiled (it runs once per block or group of
    # every merge, and its ~15 numpy calls held the GIL): normalise hs[b] in place; its
    # footprint's bounding box on the target, clipped, as x0, y0, x1, y1 (x1, y1
    # exclusive, one pixel of margin); and its kind: the identity (on the same grid),
    # affine (the perspective terms move no pixel-centre corner by 0.01 px or more) or
    # perspective. Returns False if some H[2, 2] is 0.
    for b in range(len(hs)):
        scale = hs[b, 2, 2]
        if scale == 0:
            return False
        identity = True
        for i in range(3):
            for j in range(3):
                hs[b, i, j] /= scale
                if hs[b, i, j] != (1.0 if i == j else 0.0):
                    identity = False
        h = hs[b]
        lo_x, lo_y, hi_x, hi_y = np.inf, np.inf, -np.inf, -np.inf
        deviation, nowhere = 0.0, False
        for corner in range(4):
            right, bottom = corner == 1 or corner == 2, corner >= 2
            # footprint edges (the outer edges of the frame's corner pixels)
            x, y = (width - 0.5 if right else -0.5), (height - 0.5 if bottom else -0.5)
            den = x * h[2, 0] + y * h[2, 1] + h[2, 2]
            u, v = (x * h[0, 0] + y * h[0, 1] + h[0, 2]) / den, (x * h[1, 0] + y * h[1, 1] + h[1, 2]) / den
            if np.isnan(u) or np.isnan(v):
                nowhere = True
            else:
                lo_x, hi_x, lo_y, hi_y = min(lo_x, u), max(hi_x, u), min(lo_y, v), max(hi_y, v)
            # corner pixel centres, with and without the perspective terms
            x, y = (width - 1.0 if right else 0.0), (height - 1.0 if bottom else 0.0)
            den = x * h[2, 0] + y * h[2, 1] + h[2, 2]
            linear_u, linear_v = x * h[0, 0] + y * h[0, 1] + h[0, 2], x * h[1, 0] + y * h[1, 1] + h[1, 2]
            deviation = max(deviation, abs(linear_u / den - linear_u), abs(linear_v / den - linear_v))
        if nowhere:  # an empty box
            lo_x, lo_y, hi_x, hi_y = 0.0, 0.0, -1.0, -1.0
        boxes[b, 0] = min(max(np.floor(lo_x), 0.0), target_width)
        boxes[b, 1] = min(max(np.floor(lo_y), 0.0), target_height)
        boxes[b, 2] = max(min(np.ceil(hi_x) + 1.0, target_width), 0.0)
        boxes[b, 3] = max(min(np.ceil(hi_y) + 1.0, target_height), 0.0)
        kinds[b] = _IDENTITY_WARP if identity and same_grid else (
            _AFFINE_WARP if deviation < 0.01 else _PERSPECTIVE_WARP)
    return True


class WarpAccumulator:
    """Accumulates warped detection counts and frame coverage on a target grid.

    Each call to :meth:`add` warps a count image (the sum of a sub-batch of binary
    frames) and adds it, together with the number of frames behind every target pixel,
    inside the warped footprint's bounding box only. A target pixel is covered by a
    warped frame when its source position rounds to a source pixel (nearest-neighbour
    coverage, the pixel-area convention); its count is the bilinear interpolation of
    the source counts, edge pixels replicated, so a covered pixel always receives a
    full-weight sample and ``counts / frames`` stays unbiased up to the frame edge.
    Warps whose perspective terms move no footprint corner by more than 0.01 pixel run
    as affine warps (about 1.5x faster).

    Attributes:
        counts: (Ht, Wt) float32 accumulated detections.
        frames: (Ht, Wt) float32 accumulated number of binary frames per pixel.
    """

    def __init__(self, height: int, width: int) -> None:
        """Create an empty accumulator for a target grid of ``height`` x ``width`` pixels."""
        self.counts = np.zeros((height, width), dtype=np.float32)
        self.frames = np.zeros((height, width), dtype=np.float32)
        self._ones: dict[tuple[int, int], np.ndarray] = {}

    def add(self, counts: NDArray, n_frames: int, homography: NDArray[np.float64]) -> None:
        """Warp ``counts`` of ``n_frames`` binary frames by ``homography`` and accumulate.

        Args:
            counts: (H, W) detection counts (any real dtype) in source-frame pixels.
            n_frames: number of binary frames summed into ``counts``.
            homography: (3, 3) float64 map from source-frame to target pixel coordinates.
        """
        self.add_many(np.asarray(counts)[None], np.array([n_frames]), np.asarray(homography)[None])

    def add_many(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
                 weights: NDArray[np.float32] | None = None) -> None:
        """Warp and accumulate B count images at once (see :meth:`add`).

        Args:
            counts: (B, H, W) detection counts (any real dtype) in source-frame pixels.
            n_frames: (B,) number of binary frames summed into each count image.
            homographies: (B, 3, 3) float64 maps from source-frame to target pixels.
            weights: (H, W) float32 weight of each source pixel in [0, 1]; None: all 1.
                With weights, counts and frames are both warped bilinearly as
                ``weights * counts`` and ``weights * n`` (a weighted mean per target
                pixel; sparse weights such as one colour filter in four leave no
                nearest-neighbour coverage to speak of).
        """
        if weights is not None:
            self._add_weighted(counts, n_frames, homographies, np.asarray(weights, np.float32))
            return
        if not len(counts):
            return
        _, h, w = counts.shape
        th, tw = self.counts.shape
        hs = np.array(homographies, np.float64)  # normalised in place below
        boxes = np.empty((len(hs), 4), np.int64)
        kinds = np.empty(len(hs), np.int8)
        if not _footprints(hs, w, h, tw, th, (h, w) == (th, tw), boxes, kinds):
            raise ValueError("degenerate homography: H[2, 2] == 0")
        x0, y0, x1, y1 = boxes.T
        identity, affine = kinds == _IDENTITY_WARP, kinds == _AFFINE_WARP
        ones = self._ones.get((h, w))
        if ones is None:
            ones = self._ones[(h, w)] = np.ones((h, w), np.float32)
        for b in range(len(hs)):
            if identity[b]:  # e.g. every group at the first level, before any motion is known
                self.counts += counts[b]
                self.frames += np.float32(n_frames[b])
                continue
            if x1[b] <= x0[b] or y1[b] <= y0[b]:
                continue
            shifted = hs[b].copy()
            shifted[0] -= x0[b] * shifted[2]
            shifted[1] -= y0[b] * shifted[2]
            size = (int(x1[b] - x0[b]), int(y1[b] - y0[b]))
            warp, matrix = (cv2.warpAffine, shifted[:2]) if affine[b] else (cv2.warpPerspective, shifted)
            # Two single-channel warps are about 2.5x faster than one two-channel warp.
            # float32 in, float32 out: the asarray calls only type cv2's results (no copy)
            coverage = np.asarray(warp(ones, matrix, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                       borderValue=0), np.float32)
            warped = np.asarray(warp(np.asarray(counts[b], np.float32), matrix, size, flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE), np.float32)
            warped *= coverage
            self.counts[y0[b]:y1[b], x0[b]:x1[b]] += warped
            coverage *= np.float32(n_frames[b])
            self.frames[y0[b]:y1[b], x0[b]:x1[b]] += coverage

    def _add_weighted(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
                      weights: NDArray[np.float32]) -> None:
        """:meth:`add_many` with per-pixel weights: bilinear warps of weighted counts and frames."""
        _, h, w = counts.shape
        th, tw = self.counts.shape
        for b, hom in enumerate(geometry.normalize(np.asarray(homographies, np.float64))):
            x0, y0, x1, y1 = geometry.footprint_bounds(hom[None], w, h)
            x0, y0 = max(int(np.floor(x0)), 0), max(int(np.floor(y0)), 0)
            x1, y1 = min(int(np.ceil(x1)) + 1, tw), min(int(np.ceil(y1)) + 1, th)
            if x1 <= x0 or y1 <= y0:
                continue
            shifted, size = geometry.translation(-x0, -y0) @ hom, (x1 - x0, y1 - y0)
            planes = ((self.counts, counts[b] * weights), (self.frames, weights * np.float32(n_frames[b])))
            for target, image in planes:
                target[y0:y1, x0:x1] += cv2.warpPerspective(np.asarray(image, np.float32), shifted, size,
                                                            flags=cv2.INTER_LINEAR, borderValue=0)

    def merge(self, other: WarpAccumulator) -> None:
        """Add another accumulator of the same grid (e.g. one filled by another thread)."""
        self.counts += other.counts
        self.frames += other.frames


def merge_groups(source, homographies: NDArray[np.float64], starts: NDArray[np.int64],
                 stops: NDArray[np.int64], references: NDArray[np.int64],
                 subbatch_px: float) -> list[tuple[NDArray[np.float32], NDArray[np.float32]]]:
    """Warp the frames of each group into its reference frame's pixel grid and sum them.

    Paper Sec. 4, "Merge", with the photons of overlapping groups counted once: the
    frames ``min(starts):max(stops)`` are split into sub-batches (:func:`subbatch_edges`,
    with a break at every group boundary) and each sub-batch is counted once
    (``source.sum_ranges``). Then either

    - *direct*: each sub-batch is warped into every group that holds it, by the warp of
      its middle frame relative to the group's reference frame; or, when groups overlap
      so much that this would cost more warps (e.g. each frame in four groups at the
      third midpoint level),
    - *two-stage*: each sub-batch is warped once into a window grid (the first group's
      reference frame, enlarged to hold every footprint) and summed per block between
      consecutive group boundaries; each group sums its blocks and is warped once into
      its reference grid. The second bilinear resampling adds a slight symmetric blur.

    Call it on a window of consecutive groups: the window's sub-batch counts are held
    in memory.

    Args:
        source: a :class:`~photonpano.stages.PhotonSource`.
        homographies: (T, 3, 3) float64 current frame-to-panorama homographies.
        starts: (G,) int64 first frame of each group.
        stops: (G,) int64 one past the last frame of each group.
        references: (G,) int64 frame whose pixel grid receives each group.
        subbatch_px: sub-batch tolerance in pixels (corner travel, > 0).

    Returns:
        One ``(counts, frames)`` per group: (H, W) float32 warped detections (or summed
        linear intensity) and number of frames behind each pixel.
    """
    starts, stops = np.asarray(starts, np.int64), np.asarray(stops, np.int64)
    if not len(starts):
        return []
    lo, hi = int(starts.min()), int(stops.max())
    h, w = source.height, source.width
    base = np.linalg.inv(homographies[int(references[0])])
    relative = base @ homographies[lo:hi]
    boundaries = np.unique(np.concatenate([starts, stops])) - lo
    edges = subbatch_edges(relative, w, h, subbatch_px, breaks=boundaries,
                           frame_step=source.frame_step, first_frame=lo)
    counts = source.sum_ranges(lo + edges)
    middles = lo + (edges[:-1] + edges[1:]) // 2
    sizes = np.diff(edges)
    spans = np.searchsorted(edges, np.stack([starts - lo, stops - lo], axis=1))  # (G, 2) sub-batch ranges
    moving = not np.allclose(relative, _IDENTITY, rtol=0, atol=1e-12)
    if moving and int(np.diff(spans, axis=1).sum()) > len(sizes) + 2 * len(starts):
        return _merge_two_stage(counts, sizes, base @ homographies[middles], edges, boundaries, starts - lo,
                                stops - lo, np.linalg.inv(homographies[references]) @ np.linalg.inv(base), w, h)
    out = []
    for (b0, b1), reference in zip(spans, references):
        warps = np.linalg.inv(homographies[int(reference)]) @ homographies[middles[b0:b1]]
        if np.allclose(warps, _IDENTITY, rtol=0, atol=1e-12):
            warps = np.repeat(_IDENTITY[None], len(warps), axis=0)
        acc = WarpAccumulator(h, w)
        acc.add_many(counts[b0:b1], sizes[b0:b1], warps)
        out.append((acc.counts, acc.frames))
    return out


def _merge_two_stage(counts, sizes, to_window, edges, boundaries, starts, stops, window_to_reference,
                     width: int, height: int) -> list[tuple[NDArray[np.float32], NDArray[np.float32]]]:
    """The two-stage merge of :func:`merge_groups` (frame indices relative to the window start)."""
    x0, y0, x1, y1 = geometry.footprint_bounds(to_window, width, height)
    x0, y0 = int(np.floor(x0)), int(np.floor(y0))
    grid = geometry.translation(-x0, -y0)
    shape = (int(np.ceil(y1)) + 1 - y0, int(np.ceil(x1)) + 1 - x0)
    blocks = []
    for k0, k1 in zip(boundaries[:-1], boundaries[1:]):
        b0, b1 = np.searchsorted(edges, [k0, k1])
        acc = WarpAccumulator(*shape)
        acc.add_many(counts[b0:b1], sizes[b0:b1], grid @ to_window[b0:b1])
        blocks.append(acc)
    out = []
    inverse = np.linalg.inv(grid)
    for start, stop, to_reference in zip(starts, stops, window_to_reference):
        k0, k1 = np.searchsorted(boundaries, [start, stop])
        total = sum(blocks[k].counts for k in range(k0, k1))
        frames = sum(blocks[k].frames for k in range(k0, k1))
        assert isinstance(total, np.ndarray) and isinstance(frames, np.ndarray)  # each window spans >= 1 block
        warp = geometry.normalize(to_reference @ inverse)
        flags, size = cv2.INTER_LINEAR, (width, height)
        out.append((np.asarray(cv2.warpPerspective(total, warp, size, flags=flags, borderValue=0), np.float32),
                    np.asarray(cv2.warpPerspective(frames, warp, size, flags=flags, borderValue=0), np.float32)))
    return out
