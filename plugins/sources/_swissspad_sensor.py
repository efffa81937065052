"""SwissSPAD2 sensor corrections shared by the SwissSPAD sources (``npy-cube``, ``swissspad-bin``).

**Corrections** (:class:`SwissSpadCorrections`, applied in this order, as
``photoncube`` does):

1. ``fix``: ``colorspad`` crops rows ``2:`` and columns ``:496`` and swaps columns
   ``252:256`` with ``260:264`` (254x496, half array only); ``grayspad`` crops rows
   ``2:`` and columns ``:496`` of a half array (254x496), or of a full array with a
   blank row inserted between the halves, rows ``2:-2`` (509x496; the blank row is
   inpainted).
2. Missing pixels: colour-filtered pixels (``cfa``) and hot/dead pixels
   (``inpaint_mask``), both in the coordinates after the fix, are replaced by the mean
   of their valid 4-neighbours (the nearest valid pixels if none is valid), rounded
   stochastically (:class:`photonpano.inpainting.Inpainter`).
3. ``transforms``: rotations and flips in order (``rot90`` turns the image 90 degrees
   clockwise as displayed, like ``photoncube``'s ``Rot90``).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from photonpano.errors import SourceError
from photonpano.inpainting import Inpainter
from photonpano.plugins.sources._capture_config import ColourSourceConfig

from ._swissspad_readout import Transform

__all__ = [
    "SwissSpadCorrections",
    "SensorCorrector",
    "bundled_sensor_file",
    "load_cfa",
    "load_mask",
    "transform_shape",
    "transform_matrix",
]

_BUNDLED = {"inpaint_mask": "colorspad_inpaint_mask.npy", "cfa": "rgbw_oh_bn_color_ss2_corrected.png"}


def bundled_sensor_file(kind: Literal["inpaint_mask", "cfa"]) -> Path:
    """Return the bundled real SwissSPAD2 colour half-array mask or colour filter layout.

    Args:
        kind: ``"inpaint_mask"`` ((254, 496) bool ``.npy``, True = hot/dead pixel) or
            ``"cfa"`` (256x512 RGB PNG; white = no filter, pure red/green/blue = filter).

    Returns:
        The path inside the installed package (see ``plugins/data/SOURCES.md``).
    """
    return Path(str(resources.files("photonpano.plugins") / "data" / _BUNDLED[kind]))


class SwissSpadCorrections(ColourSourceConfig):
    """Sensor corrections shared by the SwissSPAD sources (``npy-cube``, ``swissspad-bin``).

    Not a plugin by itself: the sources' config classes inherit these fields.
    """

    fix: Literal["none", "colorspad", "grayspad"] = "none"
    """Sensor-specific fix of raw frames: ``colorspad`` (half array 256x512 -> 254x496:
    crop rows 2: and columns :496, swap columns 252:256 with 260:264), ``grayspad``
    (crop to 254x496, or 509x496 for a full array), or ``none``."""
    inpaint_mask: Literal["colorspad"] | Path | None = None
    """Hot/dead pixels to inpaint: a bool ``.npy`` (True = inpaint) or an image (non-zero =
    inpaint) in the coordinates after ``fix``; a larger mask is cropped to its top-left
    corner. ``colorspad`` selects the bundled real mask of a SwissSPAD2 colour half array."""
    cfa: Literal["colorspad"] | Path | None = None
    """Colour filter array: an RGB image (white = no filter, pure red/green/blue = that
    filter) or an ``.npy`` of codes (-1 none, 0 R, 1 G, 2 B), in the coordinates after
    ``fix`` (a larger one is cropped to its top-left corner, as ``photoncube`` does).
    Filtered pixels are treated as missing for registration and the panorama.
    ``colorspad`` selects the bundled real layout."""
    transforms: list[Transform] = []
    """Rotations and flips applied in order after the other corrections, e.g.
    ``[rot90, flip-ud]`` for the paper's panorama captures."""
    colour_panorama: bool = False
    """Also write ``panorama_rgb.npy`` / ``.tif`` / ``.png``: the colour ratios of the pixels
    behind each filter on the sharp luminance of the unfiltered ones (needs ``cfa``)."""



def _resolve(path: Literal["colorspad"] | Path | None, kind: Literal["inpaint_mask", "cfa"]) -> Path | None:
    if path == "colorspad":
        return bundled_sensor_file(kind)
    return path


def load_mask(path: Path, shape: tuple[int, int]) -> NDArray[np.bool_]:
    """Load a hot/dead pixel mask and crop it to ``shape``.

    Args:
        path: bool/0-1 ``.npy`` (True = inpaint) or an image (non-zero = inpaint).
        shape: ``(H, W)`` of the corrected frames.

    Returns:
        (H, W) bool mask.

    Raises:
        SourceError: unreadable file, or a mask smaller than ``shape``.
    """
    data = _load_2d(path, "inpaint_mask")
    mask = np.asarray(data.any(axis=-1)) if data.ndim == 3 else data.astype(bool)
    return _crop(mask, shape, path, "inpaint_mask")


def load_cfa(path: Path, shape: tuple[int, int]) -> NDArray[np.int8]:
    """Load a colour filter array layout and crop it to ``shape``.

    Args:
        path: an RGB image (white = unfiltered, pure red/green/blue = filter; any other
            colour is refused) or an ``.npy`` of int codes (-1 none, 0 R, 1 G, 2 B) or
            bools (True = filtered, colour unknown: code 3).
        shape: ``(H, W)`` of the corrected frames.

    Returns:
        (H, W) int8 codes: -1 unfiltered, 0/1/2 red/green/blue, 3 filtered (unknown).

    Raises:
        SourceError: unreadable file, unknown colours or codes, or a layout smaller
            than ``shape``.
    """
    data = _load_2d(path, "cfa")
    if path.suffix.lower() == ".npy":
        if data.dtype == np.bool_:
            codes = np.where(data, 3, -1).astype(np.int8)
        else:
            codes = data.astype(np.int8)
            if data.ndim != 2 or not np.isin(codes, [-1, 0, 1, 2, 3]).all() or not np.array_equal(codes, data):
                raise SourceError(f"source: cfa {path} must hold codes -1 (none), 0 (R), 1 (G), 2 (B)")
    else:
        rgb = data if data.ndim == 3 else np.repeat(data[..., None], 3, axis=-1)
        rgb = rgb[..., :3]
        top = 255 if rgb.dtype == np.uint8 else int(rgb.max()) or 1
        codes = np.full(rgb.shape[:2], -2, dtype=np.int8)
        codes[(rgb == top).all(-1)] = -1
        for c, colour in enumerate(([top, 0, 0], [0, top, 0], [0, 0, top])):
            codes[(rgb == colour).all(-1)] = c
        if (codes == -2).any():
            y, x = np.argwhere(codes == -2)[0]
            raise SourceError(f"source: cfa {path} has pixel ({x}, {y}) of colour {rgb[y, x].tolist()}; "
                              "expected white (no filter) or pure red, green or blue")
    return _crop(codes, shape, path, "cfa")


def _load_2d(path: Path, what: str) -> NDArray:
    if not path.is_file():
        raise SourceError(f"source: {what} {path} does not exist")
    if path.suffix.lower() == ".npy":
        from photonpano.npy_header import load_npy

        return load_npy(path, f"source: {what}")
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SourceError(f"source: {what} {path} is neither an .npy file nor an image OpenCV can decode")
    return image[..., 2::-1] if image.ndim == 3 else image  # BGR(A) -> RGB


def _crop(arr: NDArray, shape: tuple[int, int], path: Path, what: str) -> NDArray:
    if arr.ndim != 2 or arr.shape[0] < shape[0] or arr.shape[1] < shape[1]:
        raise SourceError(f"source: {what} {path} has shape {arr.shape}; expected at least {shape} "
                          "(the frame size after the sensor fix)")
    return np.ascontiguousarray(arr[:shape[0], :shape[1]])


def transform_shape(shape: tuple[int, int], transforms: Sequence[str]) -> tuple[int, int]:
    """Return ``(H, W)`` after applying ``transforms`` to frames of ``shape``."""
    h, w = shape
    for t in transforms:
        if t in ("rot90", "rot270"):
            h, w = w, h
    return h, w


def _apply_transforms(arr: NDArray, transforms: Sequence[str]) -> NDArray:
    """Rotate/flip the last two axes of ``arr`` (rows, columns)."""
    for t in transforms:
        if t == "rot90":
            arr = np.rot90(arr, -1, axes=(-2, -1))
        elif t == "rot180":
            arr = np.rot90(arr, 2, axes=(-2, -1))
        elif t == "rot270":
            arr = np.rot90(arr, 1, axes=(-2, -1))
        elif t == "flip-ud":
            arr = arr[..., ::-1, :]
        elif t == "flip-lr":
            arr = arr[..., ::-1]
    return np.ascontiguousarray(arr)


def transform_matrix(shape: tuple[int, int], transforms: Sequence[str]) -> NDArray[np.float64]:
    """Return the (3, 3) float64 map from corrected pixel coordinates to transformed ones.

    Args:
        shape: ``(H, W)`` of the frames before the transforms.
        transforms: the transforms, in order.

    Returns:
        ``M`` with ``(x', y', 1) = M @ (x, y, 1)``, pixel centres at integers; a
        frame-to-scene homography ``G`` of the untransformed frames becomes
        ``G @ inv(M)`` for the transformed ones.
    """
    h, w = shape
    m = np.eye(3)
    for t in transforms:
        if t == "rot90":  # clockwise: (x, y) -> (h - 1 - y, x)
            step = np.array([[0, -1, h - 1], [1, 0, 0], [0, 0, 1]], float)
            h, w = w, h
        elif t == "rot270":  # (x, y) -> (y, w - 1 - x)
            step = np.array([[0, 1, 0], [-1, 0, w - 1], [0, 0, 1]], float)
            h, w = w, h
        elif t == "rot180":
            step = np.array([[-1, 0, w - 1], [0, -1, h - 1], [0, 0, 1]], float)
        elif t == "flip-ud":
            step = np.array([[1, 0, 0], [0, -1, h - 1], [0, 0, 1]], float)
        else:  # flip-lr
            step = np.array([[-1, 0, w - 1], [0, 1, 0], [0, 0, 1]], float)
        m = step @ m
    return m


class SensorCorrector:
    """Applies :class:`SwissSpadCorrections` to counts of raw frames.

    Args:
        config: the source config holding the correction fields.
        raw_shape: ``(H, W)`` of the raw frames in sensor pixel order.
        layout_name: ``"half"`` or ``"full"`` when the raw frames are a SwissSPAD2
            readout, else None (the fixes then only check the frame size).
        where: the capture's name for error messages.

    Attributes:
        corrected_shape: ``(H, W)`` after the fix, before the transforms.
        shape: ``(H, W)`` of the output (after the transforms).
        missing: (H, W) bool pixels replaced by inpainting, output coordinates.
        cfa: (H, W) int8 colour filter codes in output coordinates (-1 unfiltered,
            0/1/2 R/G/B, 3 unknown colour), or None.
        hot: (H, W) bool hot/dead pixels in output coordinates.
        active: False when no correction is configured (counts pass through).

    Raises:
        SourceError: a fix that does not fit the frame size, or bad mask files.
    """

    def __init__(self, config: SwissSpadCorrections, raw_shape: tuple[int, int], layout_name: str | None,
                 where: str) -> None:
        self.fix = config.fix
        self.transforms = list(config.transforms)
        self.raw_shape = tuple(raw_shape)
        h, w = self.raw_shape
        gap = None
        if self.fix == "colorspad":
            if (h, w) != (256, 512):
                raise SourceError(f"source: {where}: fix colorspad expects raw SwissSPAD2 half-array frames of "
                                  f"256x512, got {h}x{w} (full-array colour fixes are not supported; an "
                                  "already corrected cube needs fix: none)")
            corrected = (254, 496)
        elif self.fix == "grayspad":
            if (h, w) == (256, 512):
                corrected = (254, 496)
            elif (h, w) == (512, 512):
                corrected, gap = (509, 496), 254  # row 254 is the blank row between the halves
            else:
                raise SourceError(f"source: {where}: fix grayspad expects raw SwissSPAD2 frames of 256x512 "
                                  f"(half) or 512x512 (full), got {h}x{w}")
        else:
            corrected = (h, w)
        self.corrected_shape = corrected
        self.shape = transform_shape(corrected, self.transforms)
        hot = np.zeros(corrected, bool)
        if gap is not None:
            hot[gap] = True
        inpaint = _resolve(config.inpaint_mask, "inpaint_mask")
        if inpaint is not None:
            hot |= load_mask(inpaint, corrected)
        cfa_path = _resolve(config.cfa, "cfa")
        cfa = load_cfa(cfa_path, corrected) if cfa_path is not None else None
        missing = hot | (cfa >= 0 if cfa is not None else False)
        if missing.all():
            raise SourceError(f"source: {where}: the masks leave no valid pixel")
        self.hot = _apply_transforms(hot, self.transforms)
        self.cfa = _apply_transforms(cfa, self.transforms) if cfa is not None else None
        self.missing = _apply_transforms(missing, self.transforms)
        self._inpainter = Inpainter(self.missing)
        self.active = self.fix != "none" or bool(self.transforms) or bool(self.missing.any())

    def with_missing(self, mask: NDArray[np.bool_]) -> SensorCorrector:
        """A copy that inpaints ``mask`` as well (hot or dead pixels found in the capture).

        Args:
            mask: (H, W) bool pixels to inpaint too, in output coordinates (``shape``): the
                grid :meth:`apply` returns, as :func:`photonpano.hot_pixels.find_hot_pixels` gives.

        Returns:
            The copy; its ``hot`` and ``missing`` hold ``mask`` too, so that every pixel is
            inpainted once from valid neighbours only (a defect never leaks into a filtered
            neighbour's inpainted counts) and the colour compositors leave it out of every plane.

        Raises:
            ValueError: if ``mask`` is not ``shape``, or leaves no valid pixel.
        """
        mask = np.asarray(mask, bool)
        if mask.shape != tuple(self.shape):
            raise ValueError(f"the pixels to inpaint are {mask.shape[0]}x{mask.shape[1]}, the corrected frames "
                             f"{self.shape[0]}x{self.shape[1]}")
        other = copy.copy(self)
        other.hot, other.missing = self.hot | mask, self.missing | mask
        other._inpainter = Inpainter(other.missing)
        other.active = True
        return other

    def geometry(self, counts: NDArray) -> NDArray:
        """Apply the fix and the transforms (no inpainting) to (B, Hraw, Wraw) counts."""
        c = counts
        if self.fix in ("colorspad", "grayspad"):
            if c.shape[1] == 512:  # full-array grayspad: blank row between the halves
                blank = np.zeros((len(c), 1, c.shape[2]), c.dtype)
                c = np.concatenate([c[:, :256], blank, c[:, 256:]], axis=1)[:, 2:-2, :496]
            else:
                c = c[:, 2:, :496]
            if self.fix == "colorspad":
                c = c.copy()
                c[:, :, 252:256], c[:, :, 260:264] = c[:, :, 260:264].copy(), c[:, :, 252:256].copy()
        return _apply_transforms(c, self.transforms)

    def apply(self, counts: NDArray[np.uint16], edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Correct counts of raw frames.

        Args:
            counts: (B, Hraw, Wraw) uint16 counts in sensor pixel order.
            edges: (B + 1,) int64 frame ranges the counts cover (they seed the
                stochastic rounding of inpainted pixels, so the same range always gives
                the same counts).

        Returns:
            (B, H, W) uint16 corrected counts (``H, W = self.shape``).
        """
        if not self.active:
            return counts
        return self._inpainter.apply(self.geometry(counts), np.asarray(edges, dtype=np.int64))
