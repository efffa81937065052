"""PNG outputs: the panorama in 16 bits, transparent where nothing was observed (``panorama.png``), and masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .errors import PhotonpanoError
from .photons import tone_map

__all__ = ["write_panorama_png", "write_mask_png"]


def write_panorama_png(path: Path, flux: NDArray[np.floating]) -> None:
    """Write a panorama as a 16-bit sRGB PNG, transparent where no pixel was observed.

    The file is OpenCV's 16-bit BGRA PNG (the grey level in B, G and R): image viewers,
    browsers, PIL and OpenCV (``IMREAD_UNCHANGED``) read it.

    Args:
        path: the ``.png`` file to write.
        flux: (Hc, Wc) float linear flux in photons/s, NaN where unobserved; tone-mapped
            by :func:`photonpano.photons.tone_map` (99.5th percentile to white).

    Raises:
        ValueError: if ``flux`` is not a non-empty 2-D array.
        PhotonpanoError: if the file cannot be written.
    """
    flux = _image_2d(flux, "write_panorama_png", "flux image")
    grey = tone_map(flux, bits=16)
    alpha = np.where(np.isfinite(flux), np.uint16(65535), np.uint16(0))
    _imwrite(path, np.dstack([grey, grey, grey, alpha]), 1)


def write_mask_png(path: Path, mask: NDArray[np.bool_]) -> None:
    """Write a canvas mask as an 8-bit grey PNG: 255 where ``mask`` is True, 0 elsewhere (``moving.png``).

    Args:
        path: the ``.png`` file to write.
        mask: (Hc, Wc) bool, e.g. the canvas pixels a robust compositor left observations out of.

    Raises:
        ValueError: if ``mask`` is not a non-empty 2-D array.
        PhotonpanoError: if the file cannot be written.
    """
    mask = _image_2d(mask, "write_mask_png", "mask")
    _imwrite(path, np.where(mask, np.uint8(255), np.uint8(0)), 9)


def _image_2d(image: NDArray, writer: str, what: str) -> NDArray:
    """``image`` as an array; ValueError naming ``writer`` unless it is a non-empty (H, W) array."""
    image = np.asarray(image)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(f"{writer}: expected a non-empty (H, W) {what}, got shape {image.shape}")
    return image


def _imwrite(path: Path, image: NDArray, compression: int) -> None:
    """Write ``image`` as a PNG at ``path`` (zlib level ``compression``); PhotonpanoError on failure."""
    import cv2

    try:
        ok = cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, compression])
    except cv2.error as exc:
        raise PhotonpanoError(f"cannot write {path}: {exc}") from None
    if not ok:
        raise PhotonpanoError(f"cannot write {path}")
