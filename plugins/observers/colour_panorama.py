"""Observer ``colour-panorama``: writes the colour panorama of a colour-filtered capture.

The SwissSPAD2 colour half array has red, green or blue filters on one pixel in four
(``cfa``). For registration and the main panorama those pixels are treated as missing
(inpainted, see :mod:`photonpano.plugins.sources._swissspad_sensor`). With ``source: {colour_panorama: true}``
(the SwissSPAD sources, or ``simulate`` with ``cfa``) the panorama stage composites the
colour panorama in the same pass as the panorama
(:class:`~photonpano.plugins.compositors.colour.ColourPanorama`: luminance-guided
demosaic through motion, ``panorama.colour``) and this observer writes it
(``photonpano_panorama_finished``). Only for a panorama without colour does it composite
the same colour itself (:func:`colour_panorama`) on the run's homographies and canvas,
from the capture still open. Hot/dead pixels are left out.

Outputs in the run folder: ``panorama_rgb.npy`` ((Hc, Wc, 3) float32 linear flux in
photons/s per channel, R, G, B; NaN where a channel saw nothing), the same as a float32
RGB TIFF with its validity mask ``panorama_rgb.tif`` (see :mod:`photonpano.hdr`) and
``panorama_rgb.png`` (16-bit sRGB, one white point for all channels).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.plugins.compositors.colour import CfaChannels, LumaGuided, cfa_corrector
from photonpano.stages import Compositor

__all__ = ["CfaChannels", "colour_panorama"]


def colour_panorama(source: Any, homographies: NDArray[np.float64], canvas_shape: tuple[int, int], *,
                    make: Callable[[], Compositor] | None = None, subbatch_px: float = 0.25,
                    chunk_batches: int = 128, progress: Callable[[int], None] | None = None,
                    executor: Any = None, guided: bool = True) -> NDArray[np.float32]:
    """Composite the colour panorama of a colour-filtered capture onto a canvas.

    Args:
        source: a colour-filtered source (``npy-cube``, ``swissspad-bin`` or ``simulate``
            with ``cfa``) whose ``corrector.cfa`` holds colour codes (0 R, 1 G, 2 B).
        homographies: (T, 3, 3) float64 frame-to-canvas homographies (the run's
            ``homographies.npy``).
        canvas_shape: ``(Hc, Wc)`` of the canvas.
        make: builds the spec's compositor (default: the bilinear ``flux-canvas``): its
            scale and robust merge's exposures for ``guided``, else each channel's compositor.
        subbatch_px: frames whose warps differ by less than this (canvas pixels) are
            composited together.
        chunk_batches: sub-batches counted per read of the source.
        progress: called with the number of binary frames done.
        executor: runs chunks in parallel (None: serially).
        guided: the panorama stage's luminance-guided colour
            (:class:`~photonpano.plugins.compositors.colour.LumaGuided`); False: the
            per-plane merge (:class:`~photonpano.plugins.compositors.colour.CfaChannels`).

    Returns:
        (Hc, Wc, 3) float32 flux in photons/s (R, G, B); NaN where unobserved.

    Raises:
        ValueError: if the source has no colour filter codes.
    """
    from photonpano.compose import BilinearCompositor, compose

    corrector = cfa_corrector(source, "colour_panorama")
    make = make or BilinearCompositor
    built = make()  # the robust merge's exposures too: a moving object is left out of the colour alike
    channels = (LumaGuided(built.scale, corrector, exposures=getattr(built, "exposures", None)) if guided
                else CfaChannels(make, corrector))
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

    rgb = getattr(panorama, "colour", None)
    if rgb is None:
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
