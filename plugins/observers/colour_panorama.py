"""Observer ``colour-panorama``: a colour panorama from a colour-filtered SwissSPAD.

The SwissSPAD2 colour half array has red, green or blue filters on one pixel in four
(``cfa``). For registration and the main panorama those pixels are treated as missing
(inpainted, see :mod:`photonpano.plugins.sources._swissspad_sensor`). With ``source: {colour_panorama: true}``
this observer then composites each colour channel from the pixels behind that filter
only, with the spec's compositor (:class:`CfaChannels`), the run's homographies and
canvas, from the capture still open (``photonpano_panorama_finished``): the dense
sub-pixel motion fills each channel's sparse pixel grid in. Hot/dead pixels are left
out.

Outputs in the run folder: ``panorama_rgb.npy`` ((Hc, Wc, 3) float32 linear flux in
photons/s per channel, R, G, B; NaN where a channel saw nothing), the same as a float32
RGB TIFF with its validity mask ``panorama_rgb.tif`` (see :mod:`photonpano.hdr`) and
``panorama_rgb.png`` (16-bit sRGB, one white point for all channels).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.stages import Compositor

__all__ = ["CfaChannels", "colour_panorama"]


class CfaChannels(Compositor):
    """The R, G and B channels of a colour-filtered capture, each by its own compositor.

    Reads the raw counts (geometry fixed, filtered pixels not inpainted) and feeds
    channel c's compositor with the pixels behind filter c only (per-pixel weights, see
    :meth:`~photonpano.stages.Compositor.feed`); :meth:`finish` stacks the channels.

    Args:
        make: builds one (unprepared) compositor per channel, e.g. a compositor
            config's ``build``.
        corrector: the source's :class:`~photonpano.plugins.sources._swissspad_sensor.SensorCorrector`, whose
            ``cfa`` holds colour codes (0 R, 1 G, 2 B) and ``hot`` the pixels to drop.
    """

    def __init__(self, make: Callable[[], Compositor], corrector: Any) -> None:
        """Build the three channel compositors."""
        self._make, self._corrector = make, corrector
        self._parts = [make() for _ in range(3)]
        self.scale = self._parts[0].scale
        self._weights = np.stack([(corrector.cfa == c) & ~corrector.hot for c in range(3)]).astype(np.float32)

    def prepare(self, canvas: Any, source: Any) -> None:
        """Prepare each channel's compositor on ``canvas``."""
        self._canvas, self._source = canvas, source
        for part in self._parts:
            part.prepare(canvas, source)

    def read(self, source: Any, edges: NDArray[np.int64]) -> NDArray:
        """Raw counts with the sensor geometry fixed and filtered pixels kept."""
        return self._corrector.geometry(source.raw_sums(edges))

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Feed each channel the pixels behind its filter (times ``weights`` if given)."""
        for part, channel in zip(self._parts, self._weights):
            part.feed(counts, n_frames, homographies, channel if weights is None else channel * weights)

    def fork(self) -> CfaChannels | None:
        """An empty copy on the same canvas, if the channel compositors fork."""
        parts = [part.fork() for part in self._parts]
        if any(part is None for part in parts):
            return None
        other = copy.copy(self)
        other._parts = parts
        return other

    def join(self, other: Compositor) -> None:
        """Add a fork's channels."""
        for part, theirs in zip(self._parts, other._parts):
            part.join(theirs)

    def finish(self) -> Any:
        """The :class:`~photonpano.compose.Panorama` with (Hc, Wc, 3) flux and frames."""
        from photonpano.compose import Panorama

        panos = [part.finish() for part in self._parts]
        return Panorama(flux=np.stack([p.flux for p in panos], axis=-1),
                        frames=np.stack([p.frames for p in panos], axis=-1),
                        homographies=panos[0].homographies)


def colour_panorama(source: Any, homographies: NDArray[np.float64], canvas_shape: tuple[int, int], *,
                    make: Callable[[], Compositor] | None = None, subbatch_px: float = 0.25,
                    chunk_batches: int = 128, progress: Callable[[int], None] | None = None,
                    executor: Any = None) -> NDArray[np.float32]:
    """Composite each colour channel of a colour-filtered capture onto a canvas.

    Args:
        source: a SwissSPAD source (``npy-cube`` or ``swissspad-bin``) whose
            ``corrector.cfa`` holds colour codes (0 R, 1 G, 2 B).
        homographies: (T, 3, 3) float64 frame-to-canvas homographies (the run's
            ``homographies.npy``).
        canvas_shape: ``(Hc, Wc)`` of the canvas.
        make: builds each channel's compositor (default: the bilinear ``flux-canvas``).
        subbatch_px: frames whose warps differ by less than this (canvas pixels) are
            composited together.
        chunk_batches: sub-batches counted per read of the source.
        progress: called with the number of binary frames done.
        executor: runs chunks in parallel (None: serially).

    Returns:
        (Hc, Wc, 3) float32 flux in photons/s (R, G, B); NaN where unobserved.

    Raises:
        ValueError: if the source has no colour filter codes.
    """
    from photonpano.compose import BilinearCompositor, compose

    corrector = getattr(source, "corrector", None)
    cfa = getattr(corrector, "cfa", None)
    if cfa is None or not np.isin(cfa, [0, 1, 2]).any():
        raise ValueError("colour_panorama: the source has no colour filter layout (set cfa)")
    channels = CfaChannels(make or BilinearCompositor, corrector)
    return compose(source, homographies, channels, subbatch_px=subbatch_px, chunk_batches=chunk_batches,
                   progress=progress, canvas_shape=canvas_shape, executor=executor).flux


@hookimpl
def photonpano_panorama_finished(panorama: Any, spec: Any, source: Any, out_dir: Path | None) -> None:
    """Write ``panorama_rgb.npy``/``.tif``/``.png`` when the source asks for a colour panorama (runs with a folder)."""
    if out_dir is None or not getattr(spec.source, "colour_panorama", False):
        return
    import cv2
    from photonpano.hdr import write_flux_tiff
    from photonpano.outputs import atomic_path, save_npy
    from photonpano.photons import linear_to_srgb

    rgb = colour_panorama(source, panorama.homographies, panorama.flux.shape[:2], make=spec.compositor.build,
                          subbatch_px=spec.panorama_subbatch_px)
    save_npy(out_dir / "panorama_rgb.npy", rgb)
    with atomic_path(out_dir / "panorama_rgb.tif") as tmp:
        write_flux_tiff(tmp, rgb)
    seen = np.isfinite(rgb)
    white = float(np.percentile(rgb[seen], 99.5)) if seen.any() else 1.0
    image = linear_to_srgb(np.where(seen, rgb, 0) / (white if white > 0 else 1.0))
    with atomic_path(out_dir / "panorama_rgb.png") as tmp:
        cv2.imwrite(str(tmp), np.rint(image[..., ::-1] * 65535).astype(np.uint16))
