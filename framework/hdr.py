"""High-dynamic-range panorama files: float32 TIFF of the linear flux, with its mask.

``panorama.npy`` is for Python; image tools (ImageJ/Fiji, GIMP, darktable, Photoshop,
``tifffile``, OpenCV's ``IMREAD_UNCHANGED``) open a float32 TIFF. The file holds two
pages: page 0 the (Hc, Wc) float32 linear flux in photons/s (NaN where unobserved),
page 1 the (Hc, Wc) uint8 validity mask (255 observed, 0 not). A colour panorama is
written the same way with an (Hc, Wc, 3) RGB page 0.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .errors import PhotonpanoError

__all__ = ["write_flux_tiff", "read_flux_tiff"]


def write_flux_tiff(path: Path, flux: NDArray[np.float32]) -> None:
    """Write a linear flux image and its validity mask as a two-page float32 TIFF.

    Args:
        path: the ``.tif`` file to write (replaced if it exists).
        flux: (Hc, Wc) or (Hc, Wc, 3) float linear flux in photons/s; NaN marks
            unobserved pixels (the mask is 0 where any channel is NaN).

    Raises:
        PhotonpanoError: if the file cannot be written.
    """
    import tifffile

    flux = np.asarray(flux, np.float32)
    valid = np.isfinite(flux) if flux.ndim == 2 else np.isfinite(flux).all(axis=-1)
    description = json.dumps({"quantity": "linear flux", "unit": "photons/s", "pages": ["flux", "mask"],
                              "mask": "255 observed, 0 unobserved (flux is NaN there)"})
    try:
        with tifffile.TiffWriter(path) as tif:
            tif.write(flux, photometric="rgb" if flux.ndim == 3 else "minisblack", description=description,
                      compression="zlib", metadata=None)
            tif.write(valid.astype(np.uint8) * np.uint8(255), photometric="minisblack", compression="zlib",
                      metadata=None)
    except OSError as exc:
        raise PhotonpanoError(f"cannot write {path}: {exc.strerror or exc}") from None


def read_flux_tiff(path: Path) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Read a file written by :func:`write_flux_tiff`.

    Returns:
        ``(flux, valid)``: float32 flux in photons/s and its (Hc, Wc) bool mask.
    """
    import tifffile

    with tifffile.TiffFile(path) as tif:
        return tif.pages[0].asarray(), tif.pages[1].asarray() > 0
