"""Views of a panorama: the panorama resampled into the pixel grids of frames, as merged frames.

The mosaic scheme registers each merged frame against its view (:mod:`photonpano.schemes.mosaic`),
the agreement check compares merged frames with theirs (:func:`photonpano.quality.panorama_agreement`)
and the video renders them (:mod:`photonpano.video`). A leaf of the run's trip: it calls
only OpenCV and the tone map of :mod:`photonpano.photons`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .records import MergedFrames, Panorama

__all__ = ["panorama_views"]


def panorama_views(panorama: Panorama, to_canvas: NDArray[np.float64], height: int, width: int,
                   min_frames: float, exposure_s: float | None = None) -> MergedFrames:
    """Resample a panorama into the pixel grids of some frames, as merged frames.

    Args:
        panorama: a :class:`Panorama` (flux in photons/s, NaN where unseen).
        to_canvas: (G, 3, 3) float64 frame-to-canvas homographies of the G frames.
        height: frame height in pixels.
        width: frame width in pixels.
        min_frames: canvas pixels observed by fewer binary frames are not trusted.
        exposure_s: the views' ``exposure_s`` (:class:`~photonpano.records.MergedFrames`):
            the binary frame exposure of the capture behind the panorama, None for
            intensity frames.

    Returns:
        G :class:`~photonpano.stages.MergedFrames`: bilinear flux (0 where unseen),
        nearest frame counts, tone-mapped images, and masks of pixels whose bilinear
        neighbourhood is trusted on the canvas.
    """
    import cv2

    from .photons import tone_map

    seen = (panorama.frames >= min_frames) & np.isfinite(panorama.flux)
    trusted = cv2.erode(seen.astype(np.uint8), np.ones((3, 3), np.uint8))
    flux = np.where(trusted > 0, panorama.flux, 0).astype(np.float32)
    g = len(to_canvas)
    shape = (g, height, width)
    out = MergedFrames(flux=np.empty(shape, np.float32), frames=np.empty(shape, np.float32),
                       images=np.empty(shape, np.uint8), masks=np.empty(shape, bool), exposure_s=exposure_s)
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
