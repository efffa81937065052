"""Inpainting: a pixel's counts replaced by its valid neighbours', in every frame range read.

:class:`Inpainter` replaces the counts of missing pixels (hot, dead or behind a colour
filter) by the mean of their valid 4-neighbours, rounded stochastically; the SwissSPAD
sources' corrector uses it for the sensor's own masks, and :class:`InpaintedSource` for
the hot and dead pixels :func:`photonpano.hot_pixels.find_hot_pixels` finds in a capture.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .stages import PhotonSource

__all__ = ["Inpainter", "InpaintedSource"]


class Inpainter:
    """Replaces the counts of missing pixels by the mean of their valid 4-neighbours.

    A missing pixel without a valid 4-neighbour averages the valid pixels of the smallest
    square ring around it that holds one. The mean is rounded stochastically (seeded by
    the frame range), so its expectation is exact, the same range always gives the same
    counts, and the result stays an integer count.

    Args:
        missing: (H, W) bool, True where a pixel's counts are to be replaced.

    Raises:
        ValueError: if every pixel is missing.
    """

    def __init__(self, missing: NDArray[np.bool_]) -> None:
        missing = np.asarray(missing, bool)
        if missing.all():
            raise ValueError("every pixel is missing: nothing to inpaint from")
        self.missing = missing
        self._index, self._sources, self._weights = _inpaint_operator(missing)

    def apply(self, counts: NDArray[np.uint16], edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Inpaint (B, H, W) uint16 ``counts`` of the frame ranges ``edges`` ((B + 1,) int64).

        Writes into ``counts`` where it is a writeable contiguous array (a copy otherwise)
        and returns the result.
        """
        if len(self._index) and len(counts):
            if not (counts.flags.c_contiguous and counts.flags.writeable):
                counts = np.array(counts)
            flat = counts.reshape(len(counts), -1)
            values = (self._weights @ flat[:, self._sources].T.astype(np.float32)).T  # (B, n_missing)
            lengths = np.diff(np.asarray(edges, dtype=np.int64))
            noise = np.stack([np.random.default_rng([int(a), int(n), 0x5EED]).random(len(self._index),
                                                                                       dtype=np.float32)
                              for a, n in zip(edges[:-1], lengths)])
            flat[:, self._index] = np.clip(np.floor(values + noise), 0, lengths[:, None]).astype(np.uint16)
        return counts


def _inpaint_operator(missing: NDArray[np.bool_]):
    """Return ``(index, sources, W)``, the inpainting operator of ``missing``.

    (n,) int64 flat indices of the missing pixels, (m,) int64 flat indices of the valid
    pixels they read, and a sparse (n, m) float32 averaging matrix (None when no pixel is
    missing: scipy.sparse, 0.1 s to import, is then not needed).
    """
    h, w = missing.shape
    ys, xs = np.nonzero(missing)
    if not len(ys):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), None
    from scipy.sparse import csr_matrix

    valid = ~missing
    ny = ys[:, None] + np.array([-1, 1, 0, 0])
    nx = xs[:, None] + np.array([0, 0, -1, 1])
    inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
    ok = inside & valid[np.clip(ny, 0, h - 1), np.clip(nx, 0, w - 1)]
    rows = [np.nonzero(ok)[0]]
    cols = [(ny * w + nx)[ok]]
    for i in np.nonzero(~ok.any(axis=1))[0]:  # rare: no valid 4-neighbour
        y, x, r = ys[i], xs[i], 1
        while True:
            y0, y1, x0, x1 = max(y - r, 0), min(y + r + 1, h), max(x - r, 0), min(x + r + 1, w)
            found = np.argwhere(valid[y0:y1, x0:x1]) + (y0, x0)
            if len(found):
                break
            r += 1
        rows.append(np.full(len(found), i))
        cols.append(found[:, 0] * w + found[:, 1])
    rows_a = np.concatenate(rows).astype(np.int64)
    cols_a = np.concatenate(cols).astype(np.int64)
    sources, local = np.unique(cols_a, return_inverse=True)
    n = np.bincount(rows_a, minlength=len(ys))
    matrix = csr_matrix(((1.0 / n[rows_a]).astype(np.float32), (rows_a, local)), shape=(len(ys), len(sources)))
    return (ys * w + xs).astype(np.int64), sources.astype(np.int64), matrix


class InpaintedSource(PhotonSource):
    """A capture whose defective pixels are inpainted in every frame range read.

    Every attribute but :meth:`sum_ranges` is the wrapped capture's (its size, rate,
    ground truth, ``raw_sums``...), and ``corrector`` for a capture that corrects its raw
    counts (the SwissSPAD sources, ``simulate`` with ``cfa``): there the defects join the
    sensor's own missing pixels (``SensorCorrector.with_missing``), so each pixel is
    inpainted once, from valid neighbours only, and the colour compositors, which read
    ``raw_sums`` through ``corrector``, leave the defects out too.

    Args:
        source: the binary capture.
        mask: (H, W) bool defective pixels (:attr:`photonpano.hot_pixels.HotPixels.mask`).

    Attributes:
        mask: ``mask``, as given.
        inpainter: the :class:`Inpainter` of ``mask`` applied after the capture's own
            counts, or None where ``corrector`` inpaints it.

    Raises:
        ValueError: if ``mask`` holds every pixel (:class:`Inpainter`), or is not the
            corrector's frame size.
    """

    def __init__(self, source: PhotonSource, mask: NDArray[np.bool_]) -> None:
        self.source, self.mask = source, np.asarray(mask, bool)
        corrector: Any = getattr(source, "corrector", None)
        self.inpainter: Inpainter | None = None
        if hasattr(corrector, "with_missing") and hasattr(source, "raw_sums"):  # sum_ranges: apply(raw_sums)
            self.corrector = corrector.with_missing(mask)
        else:
            self.inpainter = Inpainter(mask)
        # PhotonSource declares these with class defaults, which attribute lookup finds
        # before __getattr__: the wrapped capture's own values are copied
        for name in ("n_frames", "height", "width", "exposure_s", "frame_rate_hz", "ground_truth", "scene_flux",
                     "scene_pitch", "name", "kind", "frame_step"):
            setattr(self, name, getattr(source, name))

    def __getattr__(self, name: str) -> Any:
        if name in ("source", "mask", "inpainter", "corrector"):  # not set yet (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.source, name)

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16] | NDArray[np.float32]:
        """The wrapped capture's counts (see :meth:`PhotonSource.sum_ranges`), defective pixels inpainted."""
        edges = np.asarray(edges, dtype=np.int64)
        if self.inpainter is None:
            raw_sums: Any = getattr(self.source, "raw_sums")
            return self.corrector.apply(raw_sums(edges), edges)
        return self.inpainter.apply(np.asarray(self.source.sum_ranges(edges)), edges)

    def describe(self) -> dict[str, Any]:
        """The wrapped capture's summary (see :meth:`PhotonSource.describe`)."""
        return self.source.describe()
