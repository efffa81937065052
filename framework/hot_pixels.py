"""Hot and dead pixels: found in the capture's own photon counts and inpainted.

A SPAD array has pixels whose dark count rate is far above the rest (hot pixels, a few
percent of a SwissSPAD2) and pixels that never fire (dead). Their detection probability
is fixed on the sensor, not on the scene, so under camera motion they are a pattern that
stays still while the scene moves: it pulls every registration toward no motion (one
percent of hot pixels put a sunset's trajectory 1.3 px off) and prints a streak along the
trajectory into the panorama.

:func:`find_hot_pixels` finds them without a dark frame, from the capture itself. It
reads ``segments`` short stretches spread over the capture, each as two halves, and takes
every pixel's detection rate against the median of its 3x3 neighbourhood (the residual;
on a colour-filtered sensor, against the luminance around it, times its colour's ratio to
the luminance nearby for a pixel behind a filter). A pixel is defective where

1. its residual over all stretches is more than ``sigmas`` standard deviations from zero
   (binomial noise of its neighbourhood's rate plus the scene's own spread of residuals, robustly
   estimated over the frame: a median absolute deviation), either sign;
2. in no stretch does its residual stand :data:`OPPOSITE_SIGMAS` standard deviations on
   the other side: a pixel of the scene changes as the camera carries other detail over
   it, a defect stays (a stuck-low pixel's residual only falls to noise where the scene
   is as dark as it); and it stands that far on its side in at least half the stretches
   (a star crossing a pixel of a slow pan does in one or two);
3. it is isolated: at most :data:`MAX_CLUSTER` such pixels touch (a bright line of the
   scene is many);
4. the scene moved between the first and the last stretch: the halves of one stretch show
   the scene's detail alike (their residual maps correlate significantly) and the first
   stretch's halves correlate with the last's less than half as well. In a still capture
   a defect and a sharp detail of the scene look alike, and none is flagged.

:class:`~photonpano.inpainting.Inpainter` replaces each flagged pixel's counts by the mean
of its valid 4-neighbours, rounded stochastically so that its expectation is exact and the
counts stay integers (the SwissSPAD sources use it for their ``inpaint_mask`` too), and
:class:`~photonpano.inpainting.InpaintedSource` applies it to every frame range a stage
reads (on a colour-filtered sensor, together with the sensor's own missing pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .inpainting import InpaintedSource
from .stages import PhotonSource

__all__ = ["HotPixels", "find_hot_pixels", "with_hot_pixels_inpainted", "COLOUR_NEIGHBOURS", "MAX_CLUSTER",
           "OPPOSITE_SIGMAS", "STILL_SIGNIFICANCE"]

MAX_CLUSTER = 6
"""Most flagged pixels that may touch (8-connected) and still be taken for defects."""

OPPOSITE_SIGMAS = 3.0
"""A defect's residual stands this many of a stretch's standard deviations on its side in
at least half the stretches, and in none on the other side."""

COLOUR_NEIGHBOURS = 8
"""A pixel of a colour-filtered capture is compared with the median over itself and this
many nearest pixels behind the same filter, or none, as the 3x3 median of a monochrome
one holds the pixel and its 8 neighbours (on the SwissSPAD2 colour layout: unfiltered
pixels within 2 px, filtered ones within 4-6 px). Even: the median is then one of them."""

EDGE_PX = 3
"""A colour-filtered capture's frame is extended by replicating its edge this many pixels
(its filtered pixels' nearest same-filter pixels lie within 4-6 px)."""

MAX_RATE, FLUX_FLOOR = 1 - 1e-4, 1e-3
"""Detection rates are clipped below 1 before their flux is taken, and a colour's ratio
to the luminance adds this flux (photons per frame) to both (a dark region's ratio is 1)."""

STILL_SIGNIFICANCE = 5.0
"""The halves of one stretch show the scene's detail when their residual maps correlate by
more than this many standard errors (1 / sqrt(pixels)); a far stretch that then
correlates half as well shows the same detail: the scene stood still."""


@dataclass(frozen=True)
class HotPixels:
    """Defective pixels found in a capture (:func:`find_hot_pixels`).

    Attributes:
        mask: (H, W) bool, True at a hot or dead pixel, in the pixel grid the capture's
            ``sum_ranges`` gives (a SwissSPAD source's ``inpaint_mask`` where it has no
            ``transforms``).
        hot: number of flagged pixels brighter than their neighbourhood.
        dead: number of flagged pixels darker than their neighbourhood.
        frames: binary frames read to find them.
        moved: False when the scene did not move enough between the stretches read to
            tell a defect from the scene's detail (then nothing is flagged).
    """

    mask: NDArray[np.bool_]
    hot: int
    dead: int
    frames: int
    moved: bool

    def record(self) -> dict[str, Any]:
        """The JSON-ready ``hot_pixels`` entry of ``run.json``."""
        return {"found": int(self.mask.sum()), "hot": self.hot, "dead": self.dead,
                "fraction": round(float(self.mask.mean()), 6), "frames_read": self.frames,
                "scene_moved": self.moved}


def find_hot_pixels(source: PhotonSource, *, segments: int = 8, frames: int = 8000,
                    sigmas: float = 6.0) -> HotPixels | None:
    """Find hot and dead pixels from a capture's photon counts (see the module doc).

    On a colour-filtered capture (a ``corrector`` with ``cfa`` codes, as the SwissSPAD
    sources and ``simulate`` with ``cfa`` have) the raw counts are read, so that defects
    behind a filter are found too: an unfiltered pixel is compared with the luminance
    around it, a filtered one with that luminance times its colour's ratio to the
    luminance nearby (:data:`COLOUR_NEIGHBOURS`); the sensor's own masked pixels
    (``corrector.hot``) are never flagged.

    Args:
        source: a binary capture (its ``sum_ranges``, or ``raw_sums`` and ``corrector``).
        segments: stretches read, spread evenly from the first frame to the last.
        frames: binary frames read in all (at most the capture's).
        sigmas: a pixel's residual must exceed this many standard deviations.

    Returns:
        The :class:`HotPixels` found, or None for a capture that cannot be judged: one of
        linear intensities (``kind == "intensity"``), frames smaller than 3x3 pixels, or
        fewer than 2 frames per half stretch.
    """
    from scipy import ndimage

    n, h, w = int(source.n_frames), int(source.height), int(source.width)
    step = max(1, int(getattr(source, "frame_step", 1)))
    half = (min(frames, n) // (2 * segments)) // step * step
    if source.kind != "binary" or h < 3 or w < 3 or half < 2:
        return None
    layout = _Layout(source)
    starts = (np.linspace(0, n - 2 * half, segments) // step * step).astype(np.int64)
    rates = np.stack([layout.read(np.array([s, s + half, s + 2 * half]))
                      for s in starts]) / np.float32(half)  # (segments, 2, H, W) float32
    residual = rates - layout.reference(rates)
    stretch = residual.mean(axis=1)  # (segments, H, W)
    total = stretch.mean(axis=0)
    level = layout.reference(rates.mean(axis=(0, 1)))
    outlier = (np.abs(total) > sigmas * layout.noise(level, total, 2 * half * segments)) & layout.candidates
    # a defect never stands significantly on the other side of its neighbourhood: a pixel of
    # the scene does as the camera carries other detail over it (a stuck-low pixel's
    # residual only falls to noise where the scene there is as dark as it)
    levels = layout.reference(rates.mean(axis=1))  # (segments, H, W)
    standing = np.stack([np.sign(total) * stretch[k] / layout.noise(levels[k], stretch[k], 2 * half)
                         for k in range(segments)])  # (segments, H, W) standard deviations on the residual's side
    persistent = (outlier & ~(standing < -OPPOSITE_SIGMAS).any(axis=0)
                  & ((standing > OPPOSITE_SIGMAS).sum(axis=0) >= segments / 2))
    labels, _ = ndimage.label(persistent, structure=np.ones((3, 3), bool))
    isolated = np.bincount(labels.ravel())[labels] <= MAX_CLUSTER
    mask = persistent & isolated
    # the outliers and their neighbours, whose medians they raise, are the sensor's pattern, not the scene's
    moved = _scene_moved(residual, layout.classes[0] & ~ndimage.binary_dilation(outlier, np.ones((3, 3), bool)))
    if not moved:
        mask = np.zeros_like(mask)
    return HotPixels(mask, int((mask & (total > 0)).sum()), int((mask & (total < 0)).sum()),
                     int(2 * half * segments), moved)


class _Layout:
    """A capture's pixel classes, as :func:`find_hot_pixels` compares them.

    A monochrome capture: one class, each pixel's reference the 3x3 median of
    ``sum_ranges`` (the frame's edge replicated). A colour-filtered one
    (``corrector.cfa``), in the raw counts: the unfiltered pixels, each referenced to the
    median over itself and its :data:`COLOUR_NEIGHBOURS` nearest unfiltered pixels (the
    luminance there), and one class per filter, each pixel referenced to the luminance
    there times the median ratio to the luminance over itself and its nearest same-filter
    pixels (in flux: a colour's ratio to the luminance varies more slowly than either).
    The frame's edge is replicated :data:`EDGE_PX` pixels out, so that a pixel on it is
    compared with its own row as much as with the next (as the 3x3 median does). The
    sensor's own masked pixels (``corrector.hot``) are in no class.

    Attributes:
        classes: (H, W) bool masks, one per class (the unfiltered pixels first).
        candidates: (H, W) bool pixels that may be flagged.
    """

    def __init__(self, source: PhotonSource) -> None:
        self.source = source
        h, w = int(source.height), int(source.width)
        corrector = getattr(source, "corrector", None)
        cfa = getattr(corrector, "cfa", None)
        self.corrector = corrector if cfa is not None and hasattr(source, "raw_sums") else None
        self.classes = [np.ones((h, w), bool)]
        self.candidates = self.classes[0]
        if self.corrector is None:
            return
        from scipy.spatial import cKDTree

        usable = ~np.asarray(getattr(self.corrector, "hot", np.zeros((h, w), bool)), bool)
        codes = np.where(usable, np.asarray(cfa, np.int16), -2)  # -2: in no class
        kept = [code for code in np.unique(codes[codes > -2]) if (codes == code).sum() > COLOUR_NEIGHBOURS]
        if -1 not in kept:  # no unfiltered pixels to take the luminance from: judged as one class
            self.corrector = None
            return
        self.classes = [codes == code for code in kept]  # -1, the unfiltered pixels, first
        self.candidates = np.logical_or.reduce(self.classes)
        padded = np.pad(codes, EDGE_PX, mode="edge")
        self.grid = padded.shape
        inner = np.zeros(self.grid, bool)
        inner[EDGE_PX:-EDGE_PX, EDGE_PX:-EDGE_PX] = True

        def nearest(members: NDArray[np.bool_], of: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
            """The flat indices of ``of`` and (n, K + 1) of their nearest pixels of ``members`` (themselves first)."""
            pool, points = np.flatnonzero(members), np.argwhere(of)
            tree = cKDTree(np.column_stack(np.unravel_index(pool, self.grid)))
            _, index = tree.query(points, k=COLOUR_NEIGHBOURS + 1)
            return np.asarray(np.ravel_multi_index(points.T, self.grid), np.int64), pool[index]

        self.luminance = nearest(padded == -1, padded > -2)  # at every pixel, the edge's copies too
        self.neighbours = [nearest(padded == code, (padded == code) & inner) for code in kept[1:]]

    def read(self, edges: NDArray[np.int64]) -> NDArray[np.float32]:
        """(B, H, W) float32 counts of the frame ranges ``edges``.

        ``sum_ranges``, or the raw counts (geometry fixed) of a colour-filtered capture.
        """
        if self.corrector is None:
            return np.asarray(self.source.sum_ranges(edges), np.float32)
        raw_sums: Any = getattr(self.source, "raw_sums")
        return np.asarray(self.corrector.geometry(raw_sums(edges)), np.float32)

    def reference(self, rates: NDArray[np.float32]) -> NDArray[np.float32]:
        """Each pixel's reference rate, (..., H, W) float32 like ``rates``."""
        import cv2

        images = np.ascontiguousarray(rates, np.float32).reshape(-1, *rates.shape[-2:])
        if self.corrector is None:
            return np.stack([cv2.medianBlur(image, 3) for image in images]).reshape(rates.shape)
        edge = EDGE_PX
        rate = np.pad(images, ((0, 0), (edge, edge), (edge, edge)), mode="edge").reshape(len(images), -1)
        pixels, unfiltered = self.luminance
        luminance = np.zeros_like(rate)
        luminance[:, pixels] = _middle(rate[:, unfiltered])
        reference = luminance.copy()  # the unfiltered pixels'
        # a filtered pixel: the luminance there times its colour's ratio to the luminance
        # nearby, in flux (photons per frame), where the ratio is a constant
        flux = -np.log1p(-np.clip(rate, 0, MAX_RATE))
        luminance_flux = -np.log1p(-np.clip(luminance, 0, MAX_RATE))
        for members, nearest in self.neighbours:
            ratio = _middle((flux[:, nearest] + FLUX_FLOOR) / (luminance_flux[:, nearest] + FLUX_FLOOR))
            reference[:, members] = -np.expm1(-luminance_flux[:, members] * ratio)
        reference = reference.reshape(len(images), *self.grid)[:, edge:-edge, edge:-edge]
        return np.ascontiguousarray(reference).reshape(rates.shape)

    def noise(self, level: NDArray[np.float32], residual: NDArray[np.float32], frames: int) -> NDArray[np.float32]:
        """(H, W) standard deviation of a pixel's residual over ``frames`` frames.

        The binomial noise of its reference ``level`` (a rate), and its class's spread of
        ``residual`` (1.4826 x the median absolute deviation over the class's pixels). A
        rate is taken at least one frame from 0 and from 1: a saturated capture's pixels
        (rate 1, no spread) would otherwise be judged against a deviation of 0.
        """
        level = np.clip(level, 1.0 / frames, 1.0 - 1.0 / frames)
        spread: Any = 0.0
        for members in self.classes:
            values = residual[members]
            mad = 1.4826 * float(np.median(np.abs(values - np.median(values)))) if len(values) else 0.0
            spread = mad if len(self.classes) == 1 else np.where(members, mad, spread)
        return np.sqrt(level * (1 - level) / frames + spread ** 2)


def _middle(values: NDArray[np.floating]) -> NDArray[np.floating]:
    """The median along the last axis of an odd number of values (``np.median``'s, at a third of its cost)."""
    middle = values.shape[-1] // 2
    return np.partition(values, middle, axis=-1)[..., middle]


def _scene_moved(residual: NDArray[np.float32], keep: NDArray[np.bool_]) -> bool:
    """Whether the scene moved between the first and the last stretch (see the module doc, 4).

    ``residual`` is (segments, 2, H, W): each stretch's halves. The scene stood still when
    the halves of one stretch show its detail (their residual maps correlate significantly:
    more than :data:`STILL_SIGNIFICANCE` standard errors of a correlation over the pixels
    kept) and the first stretch's halves correlate with the last's at least half as well.
    """
    def correlation(a: NDArray[np.float32], b: NDArray[np.float32]) -> float:
        a, b = a[keep] - a[keep].mean(), b[keep] - b[keep].mean()
        denominator = float(np.sqrt((a * a).sum() * (b * b).sum()))
        return float((a * b).sum()) / denominator if denominator > 0 else 0.0

    near = float(np.mean([correlation(pair[0], pair[1]) for pair in residual]))
    far = float(np.mean([correlation(residual[0, i], residual[-1, i]) for i in (0, 1)]))
    detail = near > STILL_SIGNIFICANCE / np.sqrt(max(int(keep.sum()), 1))
    return not (detail and far >= 0.5 * near)


def with_hot_pixels_inpainted(source: PhotonSource, setting: str) -> tuple[PhotonSource, HotPixels | None]:
    """``source`` with the hot and dead pixels it shows inpainted, as the spec's ``hot_pixels`` says.

    Args:
        source: the opened capture.
        setting: ``"auto"`` (find them, :func:`find_hot_pixels`) or ``"off"``.

    Returns:
        ``(source, found)``: an :class:`InpaintedSource` where pixels were found (else
        ``source`` itself), and what was found (None with ``"off"`` or a capture that
        cannot be judged).
    """
    if setting == "off":
        return source, None
    found = find_hot_pixels(source)
    if found is None or not found.mask.any():
        return source, found
    return InpaintedSource(source, found.mask), found
