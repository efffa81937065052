"""Observer ``colour-panorama``: a colour panorama from a colour-filtered SwissSPAD.

The SwissSPAD2 colour half array has red, green or blue filters on one pixel in four
(``cfa``). For registration and the main panorama those pixels are treated as missing
(inpainted, see :mod:`photonpano.sensor`). With ``source: {colour_panorama: true}``
this observer then merges each colour channel from the pixels behind that filter
only, with the final homographies, onto the panorama's canvas: the dense sub-pixel
motion fills each channel's sparse pixel grid in. Hot/dead pixels are left out.

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

__all__ = ["colour_panorama"]


def colour_panorama(source: Any, homographies: NDArray[np.float64], canvas_shape: tuple[int, int], *,
                    subbatch_px: float = 0.25, chunk_batches: int = 128,
                    progress: Callable[[int], None] | None = None) -> NDArray[np.float32]:
    """Merge each colour channel of a colour-filtered capture onto a canvas.

    Args:
        source: a SwissSPAD source (``npy-cube`` or ``swissspad-bin``) whose
            ``corrector.cfa`` holds colour codes (0 R, 1 G, 2 B).
        homographies: (T, 3, 3) float64 frame-to-canvas homographies (the run's
            ``homographies.npy``).
        canvas_shape: ``(Hc, Wc)`` of the canvas.
        subbatch_px: frames whose warps differ by less than this (canvas pixels) are
            warped together.
        chunk_batches: sub-batches counted per read of the source.
        progress: called with the number of binary frames done.

    Returns:
        (Hc, Wc, 3) float32 flux in photons/s (R, G, B); NaN where unobserved.

    Raises:
        ValueError: if the source has no colour filter codes.
    """
    import cv2

    from photonpano import geometry
    from photonpano.photons import flux_mle
    from photonpano.warping import subbatch_edges

    corrector = source.corrector
    if corrector.cfa is None or not np.isin(corrector.cfa, [0, 1, 2]).any():
        raise ValueError("colour_panorama: the source has no colour filter layout (set cfa)")
    weights = np.stack([(corrector.cfa == c) & ~corrector.hot for c in range(3)]).astype(np.float32)
    ch, cw = canvas_shape
    sums = np.zeros((3, ch, cw, 2), np.float32)
    h, w = source.height, source.width
    edges = subbatch_edges(homographies, w, h, subbatch_px)
    for c0 in range(0, len(edges) - 1, chunk_batches):
        chunk = edges[c0:c0 + chunk_batches + 1]
        counts = corrector.geometry(source.raw_sums(chunk)).astype(np.float32)
        for b in range(len(chunk) - 1):
            hom = homographies[(chunk[b] + chunk[b + 1]) // 2]
            x0, y0, x1, y1 = geometry.footprint_bounds(hom[None], w, h)
            x0, y0 = max(int(np.floor(x0)), 0), max(int(np.floor(y0)), 0)
            x1, y1 = min(int(np.ceil(x1)) + 1, cw), min(int(np.ceil(y1)) + 1, ch)
            if x1 <= x0 or y1 <= y0:
                continue
            shifted = geometry.translation(-x0, -y0) @ hom
            n = float(chunk[b + 1] - chunk[b])
            for c in range(3):
                planes = np.stack([counts[b] * weights[c], n * weights[c]], axis=-1)
                sums[c, y0:y1, x0:x1] += cv2.warpPerspective(planes, shifted, (x1 - x0, y1 - y0),
                                                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                                             borderValue=0)
        if progress is not None:
            progress(int(chunk[-1] - chunk[0]))
    # a channel sees a canvas pixel through a fraction of the frames only: trust it from
    # half a frame on, as the main panorama does
    return np.stack([flux_mle(sums[c, ..., 0], sums[c, ..., 1], source.exposure_s) for c in range(3)], axis=-1)


@hookimpl
def photonpano_run_finished(spec: Any, summary: dict[str, Any], out_dir: Path) -> None:
    """Write ``panorama_rgb.npy``/``.png`` when the source asks for a colour panorama."""
    if not getattr(spec.source, "colour_panorama", False):
        return
    import cv2

    from photonpano.hdr import write_flux_tiff
    from photonpano.photons import linear_to_srgb

    source = spec.source.build()
    homographies = np.load(out_dir / "homographies.npy")
    shape = (int(summary["panorama"]["height"]), int(summary["panorama"]["width"]))
    rgb = colour_panorama(source, homographies, shape, subbatch_px=spec.panorama_subbatch_px)
    np.save(out_dir / "panorama_rgb.npy", rgb)
    write_flux_tiff(out_dir / "panorama_rgb.tif", rgb)
    seen = np.isfinite(rgb)
    white = float(np.percentile(rgb[seen], 99.5)) if seen.any() else 1.0
    image = linear_to_srgb(np.where(seen, rgb, 0) / (white if white > 0 else 1.0))
    cv2.imwrite(str(out_dir / "panorama_rgb.png"), np.rint(image[..., ::-1] * 65535).astype(np.uint16))
