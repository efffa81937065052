"""The panorama: canvases, the compositor driver, and the framework's bilinear compositor.

After the levels, every binary frame is composited onto one panorama canvas by a
:class:`~photonpano.stages.Compositor` plugin (``flux-canvas``, ``drizzle``, ...).
:func:`compose` streams the capture to it in sub-batches of frames whose canvas warps
differ by less than a tolerance, in bounded memory, on the executor's threads.
:func:`assemble_panorama` is the bilinear composite (:class:`BilinearCompositor`) that
the level loop also registers against; :func:`panorama_views` resamples a panorama into
frames' pixel grids.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .errors import StageError
from .executor import Executor, SerialExecutor, pure_task
from .records import Canvas, MergedFrames, Panorama
from .stages import Compositor, PhotonSource
from .watchdog import watched

__all__ = ["FOLD_RUNS", "Panorama", "Canvas", "canvas_homographies", "compose", "BilinearCompositor",
           "assemble_panorama", "panorama_views"]

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
                part.feed(part.read(source, chunk), np.diff(chunk), to_canvas[(chunk[:-1] + chunk[1:]) // 2])
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
    """

    def __init__(self, scale: float = 1.0) -> None:
        """Create an unprepared compositor at ``scale``."""
        self.scale = scale
        self._source: PhotonSource | None = None

    def prepare(self, canvas: Canvas, source: PhotonSource) -> None:
        """Start empty accumulators on ``canvas`` (see :meth:`Compositor.prepare`)."""
        from .warping import WarpAccumulator

        self._canvas, self._source = canvas, source
        self._acc = WarpAccumulator(canvas.height, canvas.width)

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Warp and add a sub-batch (see :meth:`Compositor.feed`)."""
        self._acc.add_many(counts, n_frames, homographies, weights=weights)

    def fork(self) -> BilinearCompositor:
        """An empty copy on the same canvas (see :meth:`Compositor.fork`)."""
        other = BilinearCompositor(self.scale)
        other.prepare(self._canvas, self._source)
        return other

    def join(self, other: Compositor) -> None:
        """Add a fork's sums (see :meth:`Compositor.join`)."""
        self._acc.merge(other._acc)

    def finish(self) -> Panorama:
        """The flux MLE per canvas pixel (see :meth:`Compositor.finish`)."""
        from .intensity import estimate_radiance

        flux = estimate_radiance(self._source, self._acc.counts, self._acc.frames)
        return Panorama(flux=flux, frames=self._acc.frames, homographies=self._canvas.homographies)


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


def panorama_views(panorama: Panorama, to_canvas: NDArray[np.float64], height: int, width: int,
                   min_frames: float) -> MergedFrames:
    """Resample a panorama into the pixel grids of some frames, as merged frames.

    Args:
        panorama: a :class:`Panorama` (flux in photons/s, NaN where unseen).
        to_canvas: (G, 3, 3) float64 frame-to-canvas homographies of the G frames.
        height: frame height in pixels.
        width: frame width in pixels.
        min_frames: canvas pixels observed by fewer binary frames are not trusted.

    Returns:
        G :class:`~photonpano.stages.MergedFrames`: bilinear flux (0 where unseen),
        nearest frame counts, tone-mapped images, and masks of pixels whose bilinear
        neighbourhood is trusted on the canvas.
    """
    import cv2

    from .photons import tone_map

    trusted = (panorama.frames >= min_frames) & np.isfinite(panorama.flux)
    trusted = cv2.erode(trusted.astype(np.uint8), np.ones((3, 3), np.uint8))
    flux = np.where(trusted > 0, panorama.flux, 0).astype(np.float32)
    g = len(to_canvas)
    shape = (g, height, width)
    out = MergedFrames(flux=np.empty(shape, np.float32), frames=np.empty(shape, np.float32),
                       images=np.empty(shape, np.uint8), masks=np.empty(shape, bool))
    inverse = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for i, h in enumerate(to_canvas):
        out.flux[i] = cv2.warpPerspective(flux, h, (width, height), flags=inverse, borderValue=0)
        out.frames[i] = cv2.warpPerspective(panorama.frames, h, (width, height),
                                            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0)
        out.masks[i] = cv2.warpPerspective(trusted, h, (width, height),
                                           flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0) > 0
        out.flux[i][~out.masks[i]] = np.nan
        out.images[i] = tone_map(out.flux[i])
    return out
