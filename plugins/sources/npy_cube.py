"""Source ``npy-cube``: a photon cube stored as a NumPy ``.npy`` file.

The SwissSPAD layout is ``(T, H, W/8)`` uint8, bit-packed along the width with the most
significant bit first (exactly ``np.packbits(frames, axis=-1)``); unpacked ``(T, H, W)``
bool or uint8 0/1 cubes are accepted too. Only the frames being merged are read, with
plain file reads into a bounded buffer (``chunk_mb``), so captures larger than memory
work and the resident memory does not grow with the capture. The SwissSPAD sensor
corrections of :mod:`photonpano.plugins.sources._swissspad_sensor` (``fix``, ``inpaint_mask``, ``cfa``,
``transforms``) apply to raw cubes, e.g. those written by ``photonpano convert``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.plugins.sources._capture_config import BinaryCaptureConfig
from photonpano.plugins.sources._swissspad_sensor import SwissSpadCorrections
from photonpano.stages import PhotonSource, SourceConfig
from photonpano.streaming import ReopenOnPickle

if TYPE_CHECKING:
    from photonpano.plugins.sources.zarr_cube import ZarrFrames
    from photonpano.streaming import FrameFiles


class NpyCubeConfig(SwissSpadCorrections, BinaryCaptureConfig):
    """A SwissSPAD ``.npy`` photon cube, bit-packed or unpacked, memory-mapped."""

    plugin: Literal["npy-cube"] = "npy-cube"
    path: Path
    """The ``.npy`` file."""
    layout: Literal["auto", "packed", "unpacked"] = "auto"
    """``packed``: (T, H, W/8) uint8, MSB first; ``unpacked``: (T, H, W) bool/uint8 0/1;
    ``auto``: bool is unpacked; uint8 is packed if frames sampled across the whole
    capture hold a byte above 1, or, for all-dark samples, if the sensor ``fix``
    expects 8 times the stored width."""

    def build(self) -> NpyCube:
        """Open the cube (memory-mapped, read-only)."""
        return NpyCube(self)


class NpyCube(ReopenOnPickle, PhotonSource):
    """A memory-mapped ``.npy`` photon cube (see :class:`NpyCubeConfig`).

    Pickles as its config (the file is opened again where it is unpickled), never as
    the photons (see :class:`~photonpano.streaming.ReopenOnPickle`).

    Attributes:
        cube: (T_file, H, W/8) or (T_file, H, W) read-only memory map (only its first
            frames are touched, to detect the layout; frames are read by ``frames``).
        packed: True for the bit-packed layout.
        frames: the streaming reader of the selected frames.
        corrector: the sensor corrections applied to counts.
    """

    label = "npy-cube"
    """The plugin key, as messages name the source."""
    frames: FrameFiles | ZarrFrames  # ZarrFrames: the zarr-cube source, which subclasses this one

    def __init__(self, config: NpyCubeConfig) -> None:
        """Open and check the cube.

        Raises:
            SourceError: missing or unreadable file, wrong dtype or number of
                dimensions, or a frame range outside the cube; messages name the file.
        """
        path = config.path
        if not path.is_file():
            raise SourceError(f"source (npy-cube): {path} does not exist")
        from photonpano.npy_header import load_npy

        cube = load_npy(path, "source (npy-cube)", mmap_mode="r")
        self._open(config, cube)
        if np.isfortran(cube):
            raise SourceError(f"source (npy-cube): {path} is stored in Fortran order; expected a C-ordered cube")
        from photonpano.streaming import FrameFiles, FrameSegment

        frame_bytes = int(np.prod(cube.shape[1:])) * cube.dtype.itemsize
        assert isinstance(cube, np.memmap)  # loaded with mmap_mode="r"
        self.frames = FrameFiles([FrameSegment(path, int(cube.offset) + config.start * frame_bytes, self.n_frames)],
                                 cube.shape[1:], cube.dtype, chunk_bytes=int(config.chunk_mb * 2**20))

    def _open(self, config: NpyCubeConfig, cube: Any) -> None:
        """Check a (T, H, W/8) or (T, H, W) cube array and set everything but ``frames``.

        Args:
            config: the source's config.
            cube: an array-like with ``ndim``, ``dtype``, ``shape`` and integer
                indexing of frames (a memory map, a zarr array).

        Raises:
            SourceError: wrong dtype or number of dimensions, a frame range outside the
                cube, or more frames than memory can hold results for
                (:func:`photonpano.npy_header.check_frames_fit_memory`); messages name
                the plugin and the file.
        """
        self.config = config
        path, what = config.path, f"source ({self.label})"
        if cube.ndim != 3:
            raise SourceError(f"{what}: {path} has shape {cube.shape}; expected a photon cube "
                              "(T, H, W/8) bit-packed or (T, H, W) unpacked")
        if cube.dtype not in (np.uint8, np.bool_):
            raise SourceError(f"{what}: {path} has dtype {cube.dtype}; expected uint8 "
                              "(bit-packed, or 0/1 unpacked) or bool")
        self.cube = cube
        self.packed = _is_packed(cube, config.layout, path, _expected_width(config), what=what)
        start, stop = config.frame_range(int(cube.shape[0]), path)
        from photonpano.plugins.sources._swissspad_sensor import SensorCorrector

        self.offset = start
        self.n_frames = stop - start
        from photonpano.npy_header import check_frames_fit_memory

        check_frames_fit_memory(self.n_frames, path, what)
        raw_shape = (cube.shape[1], cube.shape[2] * (8 if self.packed else 1))
        self.corrector = SensorCorrector(config, raw_shape, None, f"{self.label}({path.name})")
        self.height, self.width = self.corrector.shape
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = config.exposure_s or 1.0 / config.frame_rate_hz
        self.name = f"{self.label}({path.name}, {'packed' if self.packed else 'unpacked'})"

    def __reduce__(self) -> tuple[type, tuple[Any]]:
        # the layout found by sampling goes with the config, so reopening samples no frames
        layout = "packed" if self.packed else self.config.layout
        return type(self), (self.config.model_copy(update={"layout": layout}),)

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges, corrected (see :meth:`PhotonSource.sum_ranges`)."""
        from photonpano.photons import check_frame_edges

        edges = check_frame_edges(edges, self.n_frames)
        return self.corrector.apply(self.raw_sums(edges), edges)

    def raw_sums(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges without the sensor corrections.

        Args:
            edges: (B + 1,) strictly increasing frame indices within ``[0, n_frames]``.

        Returns:
            (B, H_file, W_file) uint16 counts in the cube's own pixel order.
        """
        from photonpano.photons import sum_packed_ranges, sum_unpacked_ranges

        h, w = self.corrector.raw_shape
        return self.frames.sum_ranges(edges, sum_packed_ranges if self.packed else sum_unpacked_ranges, (h, w))

    def describe(self) -> dict[str, Any]:
        """Return the capture summary with the file, layout and frame range."""
        return {**super().describe(), "path": str(self.config.path), "packed": self.packed,
                "start": self.offset, "fix": self.config.fix, "transforms": list(self.config.transforms)}


def _expected_width(config: NpyCubeConfig) -> int | None:
    """The raw frame width the sensor ``fix`` expects (SwissSPAD2: 512 pixels), or None."""
    return 512 if config.fix != "none" else None


def _is_packed(cube: np.ndarray, layout: str, path: Path, expected_width: int | None = None,
               samples: int = 64, what: str = "source (npy-cube)") -> bool:
    """Decide the layout from ``samples`` frames spread over the whole cube (not its first frames).

    A byte above 1 anywhere means bit-packed; if every sampled byte is 0 or 1, the
    stored width decides when the sensor width is known (W/8 stored: packed).
    """
    if cube.dtype == np.bool_:
        if layout == "packed":
            raise SourceError(f"{what}: {path} holds bool frames, which cannot be bit-packed; "
                              "use layout: unpacked or auto")
        return False
    if layout == "packed":
        return True
    total = int(cube.shape[0])
    picks = np.unique(np.linspace(0, total - 1, min(total, samples)).astype(np.int64))
    above_one = any(bool(np.asarray(cube[i]).max(initial=0) > 1) for i in picks)
    if layout == "unpacked" and above_one:
        raise SourceError(f"{what}: {path} holds bytes above 1, so it is not an unpacked "
                          "0/1 cube; use layout: packed or auto")
    if not above_one and layout == "auto" and expected_width == cube.shape[2] * 8:
        return True
    return above_one


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``npy-cube`` source."""
    return [NpyCubeConfig]


@hookimpl
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Read ``*.npy`` inputs of ``photonpano pano`` with this source."""
    if path.suffix.lower() == ".npy":
        return {"plugin": "npy-cube", "path": str(path)}
    return None
