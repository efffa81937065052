"""Synthetic data and small captures for contract tests (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

from importlib import resources
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..stages import MergedFrames, StageConfig


def builtin_source(key: str) -> type[StageConfig]:
    """Return the config class of a built-in source, found through the plugin host.

    The kit makes its captures with photonpano's own simulators (``simulate``,
    ``simulate3d``) but looks them up by their keys, as a spec does, rather than
    importing :mod:`photonpano.plugins`: the core depends on no built-in plugin.

    Args:
        key: the source's plugin key, e.g. ``"simulate"``.

    Raises:
        RuntimeError: if no source of that key is registered (photonpano's entry points
            are not installed, or the plugin failed to load).
    """
    from photonpano.host import PluginHost

    host = PluginHost()
    found = host.registry("source").get(key)
    if found is None:
        raise RuntimeError(f"photonpano.testing: the built-in source {key!r} is not registered "
                           f"({host.broken.get(key, 'is photonpano installed with its entry points?')})")
    return found


def textured_image(height: int = 160, width: int = 240, seed: int = 0) -> NDArray[np.float32]:
    """Return a crop of the bundled real photograph as linear intensity.

    Args:
        height: rows in pixels.
        width: columns in pixels.
        seed: picks the crop position (repeatable): the most detailed of 40 candidates.

    Returns:
        (height, width) float32 linear intensity in [0, 1] (the photo's sRGB values
        raised to 2.2).

    Raises:
        ValueError: if the crop is larger than the (720, 1440) resized photo.
    """
    import cv2

    # the photo is package data of the built-in plugins (plugins/data/SOURCES.md), read as a file: the kit
    # imports no plugin code
    photo = cv2.imread(str(resources.files("photonpano.plugins") / "data" / "office_equirect.jpg"),
                       cv2.IMREAD_GRAYSCALE)
    photo = cv2.resize(photo, (1440, 720), interpolation=cv2.INTER_AREA)
    if height > 720 or width > 1440:
        raise ValueError(f"textured_image: {height}x{width} is larger than the 720x1440 photo")
    # the most detailed of 40 seeded candidate crops (density of FAST corners)
    corners = cv2.FastFeatureDetector_create(threshold=25).detect(photo)
    detail = np.zeros(photo.shape, np.float32)
    for k in corners:
        detail[int(k.pt[1]), int(k.pt[0])] = 1.0
    rng = np.random.default_rng(seed)
    ys = rng.integers(0, 720 - height + 1, 40)
    xs = rng.integers(0, 1440 - width + 1, 40)
    best = int(np.argmax([detail[y:y + height, x:x + width].mean() for y, x in zip(ys, xs)]))
    y, x = int(ys[best]), int(xs[best])
    return (photo[y:y + height, x:x + width].astype(np.float32) / 255.0) ** 2.2


def merged_frames(images: list[NDArray[np.float32]],
                  masks: list[NDArray[np.bool_]] | None = None) -> MergedFrames:
    """Pack linear images into a :class:`~photonpano.stages.MergedFrames` as a merger would.

    Args:
        images: G (H, W) float32 linear intensities in [0, 1]; NaN marks unobserved pixels.
        masks: G (H, W) bool trusted pixels (default: the finite pixels).

    Returns:
        Merged frames: ``flux`` = images in photons/s (scaled by 1e5), ``images`` their
        sRGB-like uint8 tone map (0 where unobserved), ``frames`` = 500 where observed.
    """
    flux = np.stack(images).astype(np.float32) * np.float32(1e5)
    finite = np.isfinite(flux)
    mask = np.stack(masks).astype(bool) & finite if masks is not None else finite
    white = float(np.nanpercentile(flux, 99.5)) or 1.0
    tone = np.clip(np.nan_to_num(flux, nan=0.0) / white, 0, 1) ** (1 / 2.2)
    return MergedFrames(flux=flux, frames=np.where(finite, 500.0, 0.0).astype(np.float32),
                        images=np.round(tone * 255).astype(np.uint8), masks=mask)


def synthetic_pair(homography: NDArray[np.float64], height: int = 160, width: int = 240, *,
                   noise: float = 0.01, border_px: int = 4, seed: int = 0) -> MergedFrames:
    """Return two merged frames related by a known homography.

    Frame 0 (``a``) is a crop of the bundled photo; frame 1 (``b``) shows the same scene
    so that ``homography`` maps b's pixel coordinates to a's (photonpano's convention: x
    right, y down, pixel centres at integers): ``b(x) = a(H x)``. A ``border_px`` strip
    of each frame is marked unobserved (NaN flux, mask False), as in real merged frames.

    Args:
        homography: (3, 3) float64 b-to-a homography.
        height: frame height in pixels.
        width: frame width in pixels.
        noise: standard deviation of added Gaussian noise (relative to white).
        border_px: width of the unobserved strip at each frame edge.
        seed: noise and crop seed.

    Returns:
        Two merged frames (see :func:`merged_frames`).
    """
    import cv2

    margin = 40
    big = textured_image(height + 2 * margin, width + 2 * margin, seed)
    shift = np.array([[1, 0, margin], [0, 1, margin], [0, 0, 1]], np.float64)
    a = big[margin:margin + height, margin:margin + width]
    # b(x) = big(shift @ H @ x)
    b = cv2.warpPerspective(big, shift @ homography, (width, height),
                            flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    rng = np.random.default_rng(seed)
    frames, masks = [], []
    for image in (a, b):
        image = np.clip(image + rng.normal(0, noise, image.shape), 0, 1).astype(np.float32)
        mask = np.zeros(image.shape, bool)
        mask[border_px:height - border_px, border_px:width - border_px] = True
        frames.append(np.where(mask, image, np.nan).astype(np.float32))
        masks.append(mask)
    return merged_frames(frames, masks)


def corner_error_px(estimated: NDArray[np.float64], truth: NDArray[np.float64], width: int,
                    height: int) -> float:
    """Return the mean distance (pixels) between the frame corners mapped by two homographies."""
    from photonpano import geometry

    c = geometry.corners(width, height)
    return float(np.linalg.norm(geometry.apply(estimated, c) - geometry.apply(truth, c), axis=-1).mean())


def tiny_capture(frames: int = 1200, height: int = 64, width: int = 96, seed: int = 0) -> Any:
    """Return a small simulated capture with ground truth (the built-in ``simulate`` source).

    Args:
        frames: binary frames T.
        height: frame height in pixels.
        width: frame width in pixels (a multiple of 8).
        seed: photon seed.
    """
    return builtin_source("simulate")(frames=frames, height=height, width=width, flux=0.5, vibration_px=1.0,
                          speed_px_per_frame=0.01, seed=seed).build()
