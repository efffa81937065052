"""Videos of a finished run (``photonpano video``): stabilised exposures, a fly-through, each level.

Three renderings, each an H.264 MP4 (PyAV, the ``video`` extra):

- ``stabilised``: virtual exposures of ``exposure`` binary frames, evenly spaced over the
  capture, each warped onto the panorama canvas with the run's homographies by the
  bilinear compositor (:class:`~photonpano.compose.BilinearCompositor`: sub-batches of
  frames warped by :class:`~photonpano.warping.WarpAccumulator`, paper Eq. 3 per canvas
  pixel), so the scene stands still and the camera's view moves over it. Canvas pixels
  that fewer than half of an exposure's frames saw are black.
- ``flythrough``: the panorama as the camera saw it at evenly spaced binary frames (the
  panorama resampled into each frame's pixel grid, :func:`~photonpano.views.panorama_views`,
  at the canvas's resolution): a camera window moving over the panorama along the
  estimated path.
- ``levels``: every merged frame of every level that the run dumped
  (``outputs: {merged_frames: true}``, ``level_<k>/merged.npy``), warped onto the canvas
  by the final homography of its reference frame, labelled with its level.

Every frame is tone-mapped as ``panorama.png``: linear flux divided by the panorama's
99.5th percentile, clipped and sRGB-encoded (:func:`~photonpano.photons.linear_to_srgb`),
one white point for the whole clip so that its brightness does not pump.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import OutputError, PhotonpanoError
from .video_encode import VideoInfo, encode, require_av, to_codes, white_point

__all__ = ["MODES", "VideoInfo", "open_run", "white_point", "to_codes", "encode", "exposure_starts",
           "stabilised_frames", "flythrough_frames", "level_dumps", "merged_on_canvas", "default_exposure",
           "render_video"]

MODES = ("stabilised", "flythrough", "levels")
"""The renderings of :func:`render_video`."""

def open_run(folder: Path, *, source: bool = True) -> tuple[Any, Any]:
    """Read a finished run folder and reopen its capture.

    Args:
        folder: an output folder of ``photonpano run``/``pano``/``demo``.
        source: reopen the capture from ``spec.yaml``'s source section (False: skip it).

    Returns:
        ``(result, capture)``: the :class:`~photonpano.pipeline.RunResult` (``homographies``
        (T, 3, 3) float64 frame-to-canvas, ``panorama`` (Hc, Wc) float32 flux) and the
        opened :class:`~photonpano.stages.PhotonSource` (None without ``source``), the
        pixels in the run's ``hot_pixels.npy`` inpainted as the run did.

    Raises:
        PhotonpanoError: not a finished run (no ``run.json``), ``homographies.npy`` or
            ``panorama.npy`` missing or of the wrong shape, the source's plugin not
            installed, the capture unreadable or not the one the run read (frame
            count, size), or ``hot_pixels.npy`` unreadable or not a bool mask of the
            frame size; one line naming the path.
    """
    from .api import load

    folder = Path(folder)
    if not folder.is_dir():
        raise PhotonpanoError(f"{folder} is not a folder; expected a run folder written by photonpano run")
    for name, what in (("run.json", "the run summary"), ("homographies.npy", "(T, 3, 3) frame-to-canvas "
                       "homographies"), ("panorama.npy", "the (H, W) float32 panorama")):
        if not (folder / name).is_file():
            raise PhotonpanoError(f"{folder}: no {name} ({what}); expected a finished photonpano run folder")
    result = load(folder)
    h, pano = result.homographies, result.panorama
    if h.ndim != 3 or h.shape[1:] != (3, 3) or not len(h):
        raise PhotonpanoError(f"{folder / 'homographies.npy'}: expected (T, 3, 3) homographies, got shape {h.shape}")
    if pano.ndim != 2 or not pano.size:
        raise PhotonpanoError(f"{folder / 'panorama.npy'}: expected an (H, W) flux image, got shape {pano.shape}")
    if not source:
        return result, None
    if isinstance(result.spec, dict):
        plugin = result.spec.get("source", {}).get("plugin", "?")
        raise PhotonpanoError(f"{folder / 'spec.yaml'}: cannot reopen the capture: source plugin {plugin!r} is "
                              "not installed (or the spec no longer validates)")
    try:
        capture = result.spec.source.build()
    except PhotonpanoError as exc:
        raise PhotonpanoError(f"{folder}: cannot reopen the run's capture: {exc}") from None
    except (OSError, ValueError) as exc:
        raise PhotonpanoError(f"{folder}: cannot reopen the run's capture: {exc}") from None
    if capture.n_frames != len(h):
        raise PhotonpanoError(f"{folder}: the capture now holds {capture.n_frames} frames, homographies.npy "
                              f"{len(h)}; the capture changed since the run")
    hot = folder / "hot_pixels.npy"
    if hot.is_file():  # the pixels the run inpainted, inpainted again
        from .inpainting import InpaintedSource
        from .npy_header import load_npy

        mask = load_npy(hot, "the run's hot pixels")
        if mask.dtype != bool or mask.shape != (capture.height, capture.width):
            raise PhotonpanoError(f"{hot}: expected a ({capture.height}, {capture.width}) bool mask of the "
                                  f"capture's hot pixels, got {mask.dtype} {mask.shape}")
        capture = InpaintedSource(capture, mask)
    return result, capture


def exposure_starts(n_frames: int, exposure: int, count: int, step: int = 1) -> NDArray[np.int64]:
    """First frames of ``count`` exposures of ``exposure`` frames, evenly spaced over ``n_frames``.

    Starts are multiples of ``step`` (a source's cheap frame boundary) where that fits.

    Returns:
        (count,) int64 starts in ``[0, n_frames - exposure]``.

    Raises:
        PhotonpanoError: ``exposure`` outside ``[1, n_frames]`` or ``count < 1``.
    """
    if not 1 <= exposure <= n_frames:
        raise PhotonpanoError(f"--exposure must be between 1 and the capture's {n_frames} frames, got {exposure}")
    if count < 1:
        raise PhotonpanoError(f"--frames must be at least 1, got {count}")
    starts = np.rint(np.linspace(0, n_frames - exposure, count)).astype(np.int64)
    snapped = (starts // step) * step
    return np.where(snapped + exposure <= n_frames, snapped, starts)


def stabilised_frames(capture: Any, to_canvas: NDArray[np.float64], canvas_shape: tuple[int, int], exposure: int,
                      starts: NDArray[np.int64], *, subbatch_px: float = 0.25,
                      min_coverage: float = 0.5) -> Iterator[NDArray[np.float32]]:
    """Yield each virtual exposure ``starts[k]:starts[k] + exposure`` warped onto the panorama canvas.

    Args:
        capture: the opened :class:`~photonpano.stages.PhotonSource`.
        to_canvas: (T, 3, 3) float64 frame-to-canvas homographies (``homographies.npy``).
        canvas_shape: ``(Hc, Wc)`` of the panorama.
        exposure: binary frames per exposure.
        starts: (K,) int64 first frame of each exposure.
        subbatch_px: frames whose canvas warps differ by less (corner travel, canvas
            pixels) share one warp (:func:`~photonpano.warping.subbatch_edges`).
        min_coverage: canvas pixels seen by fewer than this fraction of the exposure's
            frames are NaN.

    Yields:
        (Hc, Wc) float32 flux in photons/s (mean linear intensity for intensity
        sources), NaN where the exposure did not look.
    """
    from .compose import BilinearCompositor
    from .records import Canvas
    from .warping import subbatch_edges

    canvas = Canvas(canvas_shape[0], canvas_shape[1], to_canvas)
    for start in np.asarray(starts, np.int64):
        stop = int(start) + exposure
        edges = subbatch_edges(to_canvas[start:stop], capture.width, capture.height, subbatch_px,
                               frame_step=capture.frame_step, first_frame=int(start))
        compositor = BilinearCompositor()
        compositor.prepare(canvas, capture)
        compositor.feed(capture.sum_ranges(start + edges), np.diff(edges),
                        to_canvas[start + (edges[:-1] + edges[1:]) // 2])
        pano = compositor.finish()
        yield np.where(pano.frames >= min_coverage * exposure, pano.flux, np.nan).astype(np.float32)


def flythrough_frames(panorama: NDArray[np.float32], to_canvas: NDArray[np.float64], frame_shape: tuple[int, int],
                      times: NDArray[np.int64], scale: float = 1.0, chunk: int = 16) -> Iterator[NDArray[np.float32]]:
    """Yield the panorama as the camera saw it at binary frames ``times``.

    Args:
        panorama: (Hc, Wc) float32 flux, NaN where unobserved.
        to_canvas: (T, 3, 3) float64 frame-to-canvas homographies.
        frame_shape: ``(H, W)`` of a binary frame in pixels.
        times: (K,) int64 binary frames to show.
        scale: view pixels per frame pixel (the canvas's super-resolution scale, so
            that the view is as sharp as the panorama).
        chunk: views resampled at once.

    Yields:
        (round(H * scale), round(W * scale)) float32 flux, NaN outside the panorama.
    """
    from . import geometry
    from .records import Panorama
    from .views import panorama_views

    seen = np.isfinite(panorama).astype(np.float32)
    pano = Panorama(flux=panorama, frames=seen, homographies=to_canvas)
    height, width = round(frame_shape[0] * scale), round(frame_shape[1] * scale)
    view_to_frame = np.linalg.inv(geometry.scale_matrix(scale))
    times = np.asarray(times, np.int64)
    for k in range(0, len(times), chunk):
        views = panorama_views(pano, to_canvas[times[k:k + chunk]] @ view_to_frame, height, width, 0.5)
        yield from views.flux


def level_dumps(folder: Path, n_frames: int, frame_shape: tuple[int, int]
                ) -> list[tuple[int, NDArray[np.float32], NDArray[np.int64], int]]:
    """The merged frames a run dumped per level (``level_<k>/``, see the ``level_dumps`` observer).

    Args:
        folder: the run folder.
        n_frames: binary frames T of the run.
        frame_shape: ``(H, W)`` of the capture's frames (the merged frames' shape).

    Returns:
        ``[(level, merged, references, binning)]``, levels in order: (G, H / k, W / k)
        float32 flux in photons/s (memory-mapped, NaN where unobserved) in each
        reference frame's pixel grid binned k x k (the level registered at that
        resolution; k = 1: sensor pixels), (G,) int64 reference frames and k.

    Raises:
        PhotonpanoError: no ``level_<k>/merged.npy`` in ``folder`` (the run did not set
            ``outputs.merged_frames``), or a dump unreadable or of the wrong shape.
    """
    levels = sorted((int(p.name.split("_")[1]), p) for p in Path(folder).glob("level_*")
                    if p.name.split("_")[1].isdigit() and (p / "merged.npy").is_file())
    if not levels:
        raise PhotonpanoError(f"{folder}: no level_<k>/merged.npy; --mode levels needs a run with "
                              "outputs: {merged_frames: true}")
    dumps = []
    for level, path in levels:
        try:
            merged = np.load(path / "merged.npy", mmap_mode="r", allow_pickle=False)
            refs = np.load(path / "references.npy", allow_pickle=False).astype(np.int64)
        except (OSError, ValueError) as exc:
            raise PhotonpanoError(f"{path}: cannot read the level's merged frames: {exc}") from None
        binning = frame_shape[1] // merged.shape[2] if merged.ndim == 3 and merged.shape[2] else 0
        if (not binning or merged.shape[1:] != (frame_shape[0] // binning, frame_shape[1] // binning)
                or refs.shape != (len(merged),)):
            raise PhotonpanoError(f"{path / 'merged.npy'}: expected (G, {frame_shape[0]}, {frame_shape[1]}) "
                                  "merged frames (or binned k x k) and G references, got "
                                  f"{merged.shape} and {refs.shape}")
        if len(refs) and (refs.min() < 0 or refs.max() >= n_frames):
            raise PhotonpanoError(f"{path / 'references.npy'}: reference frames outside the run's {n_frames} frames")
        dumps.append((level, merged, refs, binning))
    return dumps


def merged_on_canvas(flux: NDArray, to_canvas: NDArray[np.float64], canvas_shape: tuple[int, int]
                     ) -> NDArray[np.float32]:
    """Warp one merged frame onto the canvas by its reference frame's homography.

    Uses :meth:`~photonpano.warping.WarpAccumulator.add_many` with the frame's observed
    pixels as weights (a bilinear weighted mean, unobserved pixels left out).

    Args:
        flux: (H, W) float flux in the reference frame's pixel grid, NaN where unobserved.
        to_canvas: (3, 3) float64 merged-frame-to-canvas homography (the reference
            frame's, times :func:`~photonpano.geometry.scale_matrix` of the binning).
        canvas_shape: ``(Hc, Wc)``.

    Returns:
        (Hc, Wc) float32 flux, NaN where the frame does not reach.
    """
    from .warping import WarpAccumulator

    flux = np.asarray(flux, np.float32)
    seen = np.isfinite(flux)
    acc = WarpAccumulator(*canvas_shape)
    acc.add_many(np.where(seen, flux, 0)[None], np.ones(1, np.int64), np.asarray(to_canvas)[None],
                 weights=seen.astype(np.float32))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(acc.frames > 0.5, acc.counts / acc.frames, np.nan).astype(np.float32)


def default_exposure(summary: dict[str, Any], n_frames: int) -> int:
    """The run's level-1 group size (``run.json`` ``group_size``), else 1 % of the capture (>= 1 frame)."""
    chosen = (summary.get("group_size") or {}).get("group_size")
    if isinstance(chosen, int) and 1 <= chosen <= n_frames:
        return chosen
    return max(1, n_frames // 100)


def render_video(run: Path, output: Path, *, mode: str = "stabilised", exposure: int | None = None,
                 fps: float = 30.0, frames: int | None = None, width: int | None = None, force: bool = False,
                 advance: Callable[[int], None] | None = None,
                 start: Callable[[int], None] | None = None) -> VideoInfo:
    """Render a finished run as a video (``photonpano video``), written atomically.

    Args:
        run: the run folder (``run.json``, ``homographies.npy``, ``panorama.npy``; the
            capture ``spec.yaml`` names is reopened for ``stabilised``).
        output: the ``.mp4`` (or ``.mkv``, ``.mov``) file to write.
        mode: one of :data:`MODES` (see the module).
        exposure: binary frames per virtual exposure (``stabilised``); None: the run's
            level-1 group size.
        fps: playback frames per second.
        frames: video frames; None: one per exposure without overlap (at most 1000)
            for ``stabilised`` and ``flythrough``, every merged frame for ``levels``.
            Exposures and views are spread evenly over the capture.
        width: output width in pixels (see :func:`encode`).
        force: replace an existing ``output``.
        advance: called with 1 after each frame.
        start: called once with the number of frames before the first (a progress bar's total).

    Returns:
        The :class:`VideoInfo`.

    Raises:
        MissingDependency: PyAV is not installed (the ``video`` extra).
        OutputError: ``output`` exists (without ``force``), is a folder or a link.
        PhotonpanoError: a bad mode, exposure or frame count; not a run folder (see
            :func:`open_run`); no level dumps for ``levels``.
    """
    from . import geometry
    from .outputs.files import atomic_path, refuse_symlink

    output = Path(output)
    if mode not in MODES:
        raise PhotonpanoError(f"--mode must be one of {', '.join(MODES)}, got {mode!r}")
    if output.suffix.lower() not in (".mp4", ".mkv", ".mov"):
        raise PhotonpanoError(f"output {output}: expected a .mp4 (or .mkv, .mov) file name")
    refuse_symlink(output, "output")
    if output.is_dir():
        raise OutputError(f"output {output} is a folder; give a .mp4 file name")
    if output.exists() and not force:
        raise OutputError(f"output {output} exists; pass --force to replace it")
    if frames is not None and frames < 1:
        raise PhotonpanoError(f"--frames must be at least 1, got {frames}")
    if exposure is not None and exposure < 1:
        raise PhotonpanoError(f"--exposure must be at least 1 binary frame, got {exposure}")
    require_av()
    result, capture = open_run(run, source=mode == "stabilised")
    to_canvas, pano = result.homographies, result.panorama
    n = len(to_canvas)
    white = white_point(pano)
    labels = None
    if mode == "levels":
        source = result.summary.get("source", {})
        dumps = level_dumps(Path(run), n, (source.get("height"), source.get("width")))
        entries = [(level, merged, i, to_canvas[refs[i]] @ geometry.scale_matrix(k))
                   for level, merged, refs, k in dumps for i in range(len(refs))]
        picks = np.rint(np.linspace(0, len(entries) - 1, min(frames or len(entries), len(entries)))).astype(int)
        chosen = [entries[i] for i in np.unique(picks)]
        count = len(chosen)
        labels = iter([f"level {level}" for level, *_ in chosen])
        stream: Iterator[NDArray] = (merged_on_canvas(merged[i], h, pano.shape) for _, merged, i, h in chosen)
    elif mode == "stabilised":
        exposure = default_exposure(result.summary, n) if exposure is None else exposure
        count = frames or max(1, min(n // max(exposure, 1), 1000))
        starts = exposure_starts(n, exposure, count, capture.frame_step)
        stream = stabilised_frames(capture, to_canvas, pano.shape, exposure, starts)
    else:
        source = result.summary.get("source", {})
        scale = float(getattr(getattr(result.spec, "compositor", None), "scale", 1.0))
        count = frames or max(1, min(n // default_exposure(result.summary, n), 1000))
        times = np.rint(np.linspace(0, n - 1, count)).astype(np.int64)
        stream = flythrough_frames(pano, to_canvas, (int(source["height"]), int(source["width"])), times, scale)
    if start is not None:
        start(count)
    with atomic_path(output) as tmp:
        info = encode(tmp, stream, count, fps=fps, white=white, width=width, labels=labels, advance=advance)
    return info
