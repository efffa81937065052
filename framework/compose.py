"""The panorama: canvases, the compositor driver, and the framework's bilinear compositor.

After the levels, every binary frame is composited onto one panorama canvas by a
:class:`~photonpano.stages.Compositor` plugin (``flux-canvas``, ``drizzle``, ...).
:func:`compose` streams the capture to it in sub-batches of frames whose canvas warps
differ by less than a tolerance, in bounded memory, on the executor's threads.
:func:`assemble_panorama` is the bilinear composite (:class:`BilinearCompositor`) that
the level loop also registers against. :func:`~photonpano.views.panorama_views`, which
resamples a panorama into frames' pixel grids, lives in :mod:`photonpano.views` (re-exported here).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .errors import StageError
from .executor import Executor, SerialExecutor, pure_task
from .records import Canvas, Panorama
from .stages import Compositor, PhotonSource
from .views import panorama_views
from .watchdog import watched

__all__ = ["FOLD_RUNS", "Panorama", "Canvas", "canvas_homographies", "compose", "BilinearCompositor",
           "assemble_panorama", "panorama_views", "dither_note", "DITHER_SHARE"]

FOLD_RUNS = 8
"""Contiguous runs of chunks :func:`compose` splits a capture into, whatever the executor
(a fixed reduction order: before, one run per worker made the panorama, and the next
level's registrations, depend on the worker count by up to 7e-4 px on 20 000 frames).
Each run fills its own canvas (:meth:`~photonpano.stages.Compositor.fork`): up to this
many canvases in memory, and as many tasks in parallel."""


def canvas_homographies(homographies: NDArray[np.float64], width: int, height: int, scale: float,
                        max_pixels: int = 200_000_000) -> tuple[NDArray[np.float64], tuple[int, int]]:
    """Shift (and scale) frame-to-panorama homographies onto a canvas that holds all frames.

    Args:
        homographies: (T, 3, 3) float64 frame-to-panorama homographies.
        width: frame width in pixels.
        height: frame height in pixels.
        scale: super-resolution scale (canvas pixels per panorama pixel).
        max_pixels: refuse canvases larger than this.

    Returns:
        ``(canvas_homographies, (canvas_height, canvas_width))``.

    Raises:
        StageError: if the canvas would exceed ``max_pixels`` (the motion estimate
            diverged).
    """
    x0, y0, x1, y1 = geometry.footprint_bounds(homographies, width, height)
    shift = geometry.translation(-x0 - 0.5, -y0 - 0.5)
    out = geometry.normalize(geometry.scale_matrix(scale) @ shift @ homographies)
    cw, ch = int(np.ceil((x1 - x0) * scale)), int(np.ceil((y1 - y0) * scale))
    if cw * ch > max_pixels:
        raise StageError("panorama", "canvas", f"canvas of {cw}x{ch} pixels is too large: "
                         "the motion estimate diverged")
    return out, (ch, cw)


DITHER_SHARE = 0.02
"""Share of an even spread that a sub-pixel cell must hold for :func:`dither_note` to count it covered."""


def dither_note(homographies: NDArray[np.float64], width: int, height: int, scale: float,
                most_frames: int = 20_000) -> str | None:
    """Where a super-resolved canvas got its frames at too few sub-pixel positions, the line saying so.

    A canvas of ``scale`` s > 1 gains detail over ``scale: 1`` only where the frames'
    pixel centres land at every s-th of a frame pixel (drizzle; Fruchter and Hook, PASP
    114, 2002): the motion must dither them. Each frame pixel is cut into
    ``ceil(s) x ceil(s)`` cells; at each of a 4 x 4 grid of pixel centres, the cells its
    frames landed in are counted, and a cell counts as covered where it holds at least
    :data:`DITHER_SHARE` of an even spread. A camera that does not move covers one: the
    drizzle's finer pixels then repeat the frame pixels (a static camera over the
    dandelions at scale 2: drizzle 29.9 dB, ``flux-canvas``'s bilinear upsampling 42.9 dB
    against the scene; docs/accuracy.md).

    Args:
        homographies: (T, 3, 3) float64 frame-to-canvas homographies (canvas pixels, the
            scale included; pixel centres at integers).
        width: frame width in pixels.
        height: frame height in pixels.
        scale: canvas pixels per frame pixel.
        most_frames: at most this many frames are read, evenly spaced.

    Returns:
        One line for ``run.json``'s notes, or None where ``scale`` <= 1 or every cell is covered.
    """
    cells = int(np.ceil(scale - 1e-9))
    if cells < 2 or not len(homographies):
        return None
    chosen = homographies[np.unique(np.linspace(0, len(homographies) - 1, most_frames).astype(np.int64))]
    points = geometry.pixel_grid(width, height, 4)
    on_canvas = geometry.apply(chosen, points)  # (T', K, 2)
    seen = np.asarray(np.isfinite(on_canvas).all(axis=-1))  # (T', K)
    if not seen.any():
        return None
    cell = np.floor(np.mod(np.where(seen[..., None], on_canvas, 0) / scale, 1.0) * cells).clip(0, cells - 1)
    # per grid point: how its frames spread over the cells (a frame's other pixels are other scene points)
    index = np.arange(len(points)) * cells ** 2 + (cell[..., 1] * cells + cell[..., 0]).astype(np.int64)
    counts = np.bincount(index[seen], minlength=len(points) * cells ** 2).reshape(len(points), cells ** 2)
    share = DITHER_SHARE * seen.sum(axis=0, keepdims=True).T / cells ** 2
    covered = float(np.mean(counts >= np.maximum(share, 1)))
    if covered >= 1.0:
        return None
    return (f"super-resolution (scale {scale:g}): the frames' pixel centres landed in {covered:.0%} of the "
            f"sub-pixel cells a canvas of this scale needs (the camera barely moved), so the canvas holds no "
            "finer detail than at scale 1 and drizzle's finer pixels repeat the frame pixels; scale: 1, or "
            "compositor flux-canvas for a smooth upsampling")


def compose(source: PhotonSource, homographies: NDArray[np.float64], compositor: Compositor, *,
            subbatch_px: float = 0.25, chunk_batches: int = 128,
            progress: Callable[[int], None] | None = None,
            canvas_shape: tuple[int, int] | None = None,
            executor: Executor | None = None) -> Panorama:
    """Composite every binary frame of ``source`` onto one canvas with ``compositor``.

    Frames are summed in sub-batches whose canvas warps differ by < ``subbatch_px``
    canvas pixels (:func:`~photonpano.warping.subbatch_edges`) and fed with the warp of
    their middle frame; ``chunk_batches`` sub-batches are read from the source at once.
    The chunks are split into :data:`FOLD_RUNS` contiguous runs, each fed to its own
    :meth:`Compositor.fork` copy and added in run order: the float sums, and so the
    panorama, are the same on every executor and worker count.

    Args:
        source: the capture.
        homographies: (T, 3, 3) float64 frame-to-panorama homographies.
        compositor: a built compositor (its ``scale`` sets the canvas).
        subbatch_px: sub-batch tolerance in canvas pixels.
        chunk_batches: sub-batches counted per call to the source (bounds memory).
        progress: called with the number of binary frames done.
        canvas_shape: ``(height, width)`` to render onto a given canvas; then
            ``homographies`` already map frames to canvas pixels and ``scale`` is unused.
        executor: runs the chunk runs in parallel (None: serially).

    Returns:
        The compositor's :class:`Panorama`.

    Raises:
        StageError: if the canvas would be unreasonably large (diverged motion).
    """
    from .warping import subbatch_edges

    if canvas_shape is None:
        to_canvas, (ch, cw) = canvas_homographies(homographies, source.width, source.height, compositor.scale)
    else:
        to_canvas, (ch, cw) = geometry.normalize(homographies), canvas_shape
    with watched("compositor", compositor, "prepare"):
        compositor.prepare(Canvas(ch, cw, to_canvas), source)
    edges = subbatch_edges(to_canvas, source.width, source.height, subbatch_px,
                           frame_step=source.frame_step)
    breaks = compositor.frame_breaks(len(to_canvas), source.frame_step)
    if breaks is not None:  # split the sub-batches across them, the others as they were
        edges = np.union1d(edges, np.asarray(breaks, np.int64))
    executor = executor or SerialExecutor()
    starts = list(range(0, len(edges) - 1, chunk_batches))

    @pure_task
    def feed(part: Compositor, run: NDArray[np.int64]) -> Compositor:
        # returns what it fed, so that an executor running tasks in other processes
        # hands the filled copy back (with threads it is the same object); progress
        # reported from another process is dropped (see photonpano.progress.start_task)
        for c in run:
            executor.raise_if_cancelled()  # Ctrl-C: stop within a chunk
            chunk = edges[starts[c]:starts[c] + chunk_batches + 1]
            with watched("compositor", part, "read and feed"):
                part.feed_ranges(chunk, part.read(source, chunk), to_canvas[(chunk[:-1] + chunk[1:]) // 2])
            if progress is not None:
                progress(int(chunk[-1] - chunk[0]))
        return part

    # a fixed partition, the same for every executor and worker count, added in run order: the float sums
    # (and the panorama) do not depend on where they ran; a compositor that does not fork takes every chunk
    runs = np.array_split(np.arange(len(starts)), max(1, min(FOLD_RUNS, len(starts))))
    parts = [compositor]
    while len(parts) < len(runs):
        fork = compositor.fork()
        if fork is None:
            parts, runs = [compositor], [np.arange(len(starts))]
            break
        parts.append(fork)
    compositor, *others = executor.map(feed, parts, runs)
    for part in others:
        compositor.join(part)
    with watched("compositor", compositor, "finish"):
        return compositor.finish()


class BilinearCompositor(Compositor):
    """Backward bilinear warps of each sub-batch, then the flux MLE per canvas pixel.

    Each sub-batch's count image is warped onto the canvas (bilinear counts, nearest
    coverage, see :class:`~photonpano.warping.WarpAccumulator`) and the flux is paper
    Eq. (3) per canvas pixel (the mean linear intensity for intensity sources, see
    :func:`~photonpano.intensity.estimate_radiance`). Fast, and the reference the
    level loop registers against; bilinear interpolation blurs by about a frame pixel,
    so it cannot resolve detail finer than the frame pixels (see ``drizzle``).

    Args:
        scale: super-resolution scale (canvas pixels per frame pixel).
        exposures: virtual exposures kept apart for the robust merge
            (:func:`~photonpano.robust_merge.robust_combine`; fed through
            :meth:`feed_ranges`, a plain :meth:`feed` goes to the first); None or 1:
            every photon merged.

    Attributes:
        period_frames: the flicker period in binary frames the exposures span whole
            periods of (:meth:`expect_flicker`), or None.
        bounds: once prepared, (E + 1,) int64 first frame of each virtual exposure, then
            the frame count (:func:`~photonpano.robust_merge.exposure_bounds`).
    """

    def __init__(self, scale: float = 1.0, exposures: int | None = None) -> None:
        """Create an unprepared compositor at ``scale``."""
        self.scale = scale
        self.exposures = max(1, int(exposures or 1))
        self.period_frames: float | None = None
        self._source: PhotonSource | None = None

    def expect_flicker(self, period_frames: float) -> None:
        """Cut the virtual exposures at whole flicker periods (see :meth:`Compositor.expect_flicker`)."""
        self.period_frames = float(period_frames)

    def prepare(self, canvas: Canvas, source: PhotonSource) -> None:
        """Start empty accumulators on ``canvas`` (see :meth:`Compositor.prepare`)."""
        from .robust_merge import exposure_bounds
        from .warping import WarpAccumulator

        self._canvas, self._source = canvas, source
        self.bounds = exposure_bounds(len(canvas.homographies), self.exposures, getattr(source, "frame_step", 1),
                                       self.period_frames)
        self._acc = WarpAccumulator(canvas.height, canvas.width)  # plain feeds; the first exposure
        # the robust merge's other exposures, made when first fed (a fork holds the few its run spans)
        self._accs: list[WarpAccumulator | None] = [self._acc] + [None] * (len(self.bounds) - 2)

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Warp and add a sub-batch (see :meth:`Compositor.feed`)."""
        self._acc.add_many(counts, n_frames, homographies, weights=weights)

    def frame_breaks(self, n_frames: int, frame_step: int = 1) -> NDArray[np.int64] | None:
        """The virtual exposures' boundaries (see :meth:`Compositor.frame_breaks`); None without the robust merge."""
        return self.bounds[1:-1] if self.exposures > 1 else None

    def feed_ranges(self, edges: NDArray[np.int64], counts: NDArray, homographies: NDArray[np.float64]) -> None:
        """Warp and add a sub-batch into its virtual exposures (see :meth:`Compositor.feed_ranges`)."""
        if self.exposures == 1:
            return super().feed_ranges(edges, counts, homographies)
        from functools import partial

        from .robust_merge import feed_exposures
        from .warping import WarpAccumulator

        # a partial, not a lambda: robust_merge calls the accumulator's constructor, not back into this module
        feed_exposures(self._accs, partial(WarpAccumulator, self._canvas.height, self._canvas.width),
                       WarpAccumulator.add_many, edges, counts, homographies, self.bounds)

    def fork(self) -> BilinearCompositor:
        """An empty copy on the same canvas (see :meth:`Compositor.fork`)."""
        other = BilinearCompositor(self.scale, self.exposures)
        other.period_frames = self.period_frames
        other.prepare(self._canvas, self._source)
        return other

    def join(self, other: Compositor) -> None:
        """Add a fork's sums (see :meth:`Compositor.join`)."""
        if not isinstance(other, BilinearCompositor):
            raise TypeError(f"BilinearCompositor.join: expected a fork of this compositor, got {type(other).__name__}")
        from .robust_merge import join_exposures

        join_exposures(self._accs, other._accs, lambda mine, theirs: mine.merge(theirs))

    def exposure_sums(self) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
        """The sums of each virtual exposure apart, once every frame is fed (and the forks joined).

        Returns:
            ``(counts, frames, homographies)``: (E, H, W) float32 photon detections and
            binary frames per canvas pixel for each of the E runs of frames (:attr:`bounds`),
            in frame order (zeros for a run never fed), and the canvas's (T, 3, 3) float64
            frame-to-canvas homographies.
        """
        shape = (len(self.bounds) - 1, self._canvas.height, self._canvas.width)
        counts, frames = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        for k, acc in enumerate(self._accs):
            if acc is not None:
                counts[k], frames[k] = acc.counts, acc.frames
        return counts, frames, self._canvas.homographies

    def finish(self) -> Panorama:
        """The flux MLE per canvas pixel (see :meth:`Compositor.finish`); robust: the exposures that agree."""
        from .intensity import estimate_radiance

        moving = rejected = ranges = None
        if self.exposures > 1:
            from .robust_merge import fed_ranges, keep_exposures, robust_rejection, whole_period_frames

            fed = [a for a in self._accs if a is not None]
            counts, seen = np.stack([a.counts for a in fed]), np.stack([a.frames for a in fed])
            binary = getattr(self._source, "kind", "binary") == "binary"
            whole = whole_period_frames(self.bounds, self._accs, self.period_frames)
            rejected = robust_rejection(counts, seen, binary=binary, scale=self.scale, exposure_frames=whole)
            sums, frames, moving = keep_exposures(counts, seen, rejected)
            ranges = fed_ranges(self.bounds, self._accs)
        else:
            sums, frames = self._acc.counts, self._acc.frames
        flux = estimate_radiance(self._source, sums, frames)
        return Panorama(flux=flux, frames=frames, homographies=self._canvas.homographies, moving=moving,
                        rejected=rejected, exposure_ranges=ranges)


def assemble_panorama(source: PhotonSource, homographies: NDArray[np.float64], *, scale: float = 1.0,
                      subbatch_px: float = 0.25, chunk_batches: int = 128,
                      progress: Callable[[int], None] | None = None,
                      canvas_shape: tuple[int, int] | None = None,
                      executor: Executor | None = None) -> Panorama:
    """Warp every binary frame onto one canvas with bilinear warps (:class:`BilinearCompositor`).

    See :func:`compose` for the arguments; ``scale`` is the super-resolution scale
    (e.g. 2.0 for a canvas twice as fine).

    Returns:
        The panorama (see :class:`Panorama`).
    """
    return compose(source, homographies, BilinearCompositor(scale), subbatch_px=subbatch_px,
                   chunk_batches=chunk_batches, progress=progress, canvas_shape=canvas_shape,
                   executor=executor)
