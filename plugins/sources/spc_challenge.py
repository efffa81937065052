"""Source ``spc-challenge``: colour photon cubes of the 2026 Single Photon Challenge (``.npy``).

**Layout** (the challenge's FAQ, singlephotonchallenge.com/faq): a scene is a folder
``<SCENE-NAME>/`` of photon cubes ``<FRAME-IDX>.npy`` (ground truth ``<FRAME-IDX>.png``
beside each in the training set, the sRGB image at the cube's *last* binary frame). Each
cube is a C-ordered NumPy ``.npy`` array of shape ``(1024, 800, 100, 3)`` uint8: 1024 binary
frames of 800x800 pixels in 3 colour channels, bit-packed along the width (axis 2) most
significant bit first, exactly ``np.packbits(frames, axis=2)`` of ``(1024, 800, 800, 3)``
0/1 frames (the FAQ reads them with ``np.unpackbits(cube, axis=2)``). Pixel ``(y, x)`` of
channel ``c`` of frame ``t`` is bit ``7 - x % 8`` of byte ``cube[t, y, x // 8, c]``. The
channels are in the order red, green, blue (the order of the ground-truth PNGs they are
scored against; the FAQ does not name it: an assumption).

Registration needs one binary frame per time step. With ``channels: any`` (the default) a
pixel of the frame is 1 when any of its three channels detected a photon: the channels are
independent Bernoulli samples of fluxes ``phi_R, phi_G, phi_B`` (photons per frame), so the
result is exactly a binary frame of the flux ``phi_R + phi_G + phi_B`` (``1 - P(no photon
in any channel)`` = ``1 - exp(-(phi_R + phi_G + phi_B))``), a luminance with equal channel
weights, and the merger's photon statistics still hold. ``red``, ``green``, ``blue`` read one
channel. Several cubes (a folder, natural name order, or a list) are read as one capture,
consecutive in time; the frames of the cube(s) stream through a bounded read buffer.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.errors import SourceError
from photonpano.plugins.sources._capture_config import BinaryCaptureConfig
from photonpano.stages import PhotonSource, SourceConfig
from photonpano.streaming import ReopenOnPickle

__all__ = ["SpcChallengeConfig", "SpcChallenge", "CHALLENGE_SHAPE", "CHANNELS", "combine_channels"]

CHALLENGE_SHAPE = (1024, 800, 100, 3)
"""Shape of one challenge photon cube as stored: (T, H, W/8, C) uint8, bit-packed along the width."""

CHANNELS = ("red", "green", "blue")
"""The colour channels in stored order (last axis of a cube)."""

Channels = Literal["any", "red", "green", "blue"]


class SpcChallengeConfig(BinaryCaptureConfig):
    """Single Photon Challenge cubes: (T, H, W/8, 3) uint8 ``.npy`` files, bit-packed along the width."""

    plugin: Literal["spc-challenge"] = "spc-challenge"
    path: Path | list[Path]
    """One ``.npy`` cube, a folder of cubes (natural name order, not recursive), or a list of
    cubes in frame order; consecutive cubes are consecutive in time."""
    channels: Channels = "any"
    """Which detections form the binary frames: ``any`` (a photon in any colour channel: a
    binary frame of the summed flux R + G + B), or one channel (``red``, ``green``, ``blue``)."""

    def build(self) -> SpcChallenge:
        """Open the cubes and check their headers (reads no frames)."""
        return SpcChallenge(self)


def combine_channels(block: NDArray[np.uint8], channels: Channels) -> NDArray[np.uint8]:
    """Turn packed colour frames into packed binary frames.

    Args:
        block: (K, H, W/8, 3) uint8 frames bit-packed along the width, channels R, G, B.
        channels: ``any`` (bitwise OR of the three channels) or one channel's name.

    Returns:
        (K, H, W/8) C-contiguous uint8 frames bit-packed as the input (MSB first).
    """
    if channels == "any":
        out = np.bitwise_or(block[..., 0], block[..., 1])
        return np.bitwise_or(out, block[..., 2], out=out)
    return np.ascontiguousarray(block[..., CHANNELS.index(channels)])


def _cubes_of(config_path: Path | list[Path]) -> tuple[list[Path], str]:
    if isinstance(config_path, list):
        if not config_path:
            raise SourceError("source (spc-challenge): the list of .npy cubes is empty")
        for p in config_path:
            if not p.is_file():
                raise SourceError(f"source (spc-challenge): {p} does not exist or is not a file")
        return list(config_path), f"{len(config_path)} cubes"
    if config_path.is_dir():
        from photonpano.plugins.sources._swissspad_readout import _natural_key

        cubes = sorted((p for p in config_path.iterdir() if p.suffix.lower() == ".npy" and p.is_file()),
                       key=lambda p: _natural_key(Path(p.name)))
        if not cubes:
            raise SourceError(f"source (spc-challenge): no .npy cubes in {config_path}; expected Single Photon "
                              "Challenge photon cubes <FRAME-IDX>.npy")
        return cubes, config_path.name
    if config_path.is_file():
        return [config_path], config_path.name
    raise SourceError(f"source (spc-challenge): {config_path} does not exist")


def _open_cube(path: Path) -> tuple[tuple[int, ...], int]:
    """Check one cube's header and size; return ``(shape, data offset in bytes)``.

    Raises:
        SourceError: unreadable or truncated file, or a shape, dtype or order other than the
            challenge layout; one line naming the file and the expected layout.
    """
    from photonpano.npy_header import load_npy

    what = "source (spc-challenge)"
    cube = load_npy(path, what, mmap_mode="r")  # checks that the file holds the data its header declares
    expected = f"expected a Single Photon Challenge cube (T, H, W/8, 3) uint8, e.g. {CHALLENGE_SHAPE}"
    if cube.ndim != 4 or cube.shape[3] != 3 or cube.dtype != np.uint8:
        raise SourceError(f"{what}: {path} holds {cube.shape} {cube.dtype}; {expected}")
    if np.isfortran(cube) and cube.size > 1:
        raise SourceError(f"{what}: {path} is stored in Fortran order; {expected} in C order")
    if cube.shape[0] == 0:
        raise SourceError(f"{what}: {path} holds no frame; {expected}")
    assert isinstance(cube, np.memmap)  # loaded with mmap_mode="r"
    return tuple(int(d) for d in cube.shape), int(cube.offset)


class SpcChallenge(ReopenOnPickle, PhotonSource):
    """Single Photon Challenge photon cubes (see :class:`SpcChallengeConfig`).

    Pickles as its config (the cubes are opened again where it is unpickled).

    Attributes:
        cubes: the ``.npy`` files in frame order.
        frames: the streaming reader (:class:`~photonpano.streaming.FrameFiles`) of the
            stored (H, W/8, 3) frames of all cubes.
        references: the ground-truth PNG beside each cube (same stem), or None where absent.
    """

    def __init__(self, config: SpcChallengeConfig) -> None:
        """Open the cubes.

        Raises:
            SourceError: no cubes, a missing, unreadable or truncated file, a cube not in the
                challenge layout, cubes of different frame sizes, or a frame range outside
                the capture; messages name the file.
        """
        from photonpano.npy_header import check_frames_fit_memory
        from photonpano.streaming import FrameFiles, FrameSegment

        self.config = config
        self.cubes, label = _cubes_of(config.path)
        segments = []
        frame_shape: tuple[int, ...] | None = None
        for path in self.cubes:
            shape, offset = _open_cube(path)
            if frame_shape is None:
                frame_shape = shape[1:]
            elif shape[1:] != frame_shape:
                raise SourceError(f"source (spc-challenge): {path} holds frames of {shape[1:]} (H, W/8, C); "
                                  f"expected {frame_shape} like {self.cubes[0].name}")
            segments.append(FrameSegment(path, offset, shape[0]))
        assert frame_shape is not None
        self.frames = FrameFiles(segments, frame_shape, np.uint8, chunk_bytes=int(config.chunk_mb * 2**20))
        start, stop = config.frame_range(self.frames.n_frames, label)
        check_frames_fit_memory(stop - start, self.cubes[0], "source (spc-challenge)")
        self.offset = start
        self.n_frames = stop - start
        self.height, self.width = frame_shape[0], frame_shape[1] * 8
        self.frame_rate_hz = config.frame_rate_hz
        self.exposure_s = config.exposure_s or 1.0 / config.frame_rate_hz
        self.references = [p.with_suffix(".png") if p.with_suffix(".png").is_file() else None for p in self.cubes]
        self.name = f"spc-challenge({label}, {len(self.cubes)} cubes, channels {config.channels})"

    def read_frames(self, start: int, stop: int) -> NDArray[np.uint8]:
        """Read binary frames ``start:stop`` of the configured ``channels``.

        Args:
            start: first frame (of this source's range).
            stop: one past the last frame.

        Returns:
            (K, H, W/8) uint8 frames bit-packed MSB first (``np.packbits`` layout).

        Raises:
            ValueError: if the range leaves the capture.
        """
        from photonpano.photons import check_frame_range

        check_frame_range(start, stop, self.n_frames)
        return combine_channels(self.frames.read(self.offset + start, self.offset + stop), self.config.channels)

    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """Count detections over frame ranges (see :meth:`PhotonSource.sum_ranges`).

        Args:
            edges: (B + 1,) strictly increasing frame indices within ``[0, n_frames]``.

        Returns:
            (B, H, W) uint16 counts of the binary frames of ``channels``.

        Raises:
            ValueError: if the edges are not increasing or leave the capture.
        """
        from photonpano.photons import check_frame_edges, sum_packed_ranges

        edges = check_frame_edges(edges, self.n_frames)
        channels = self.config.channels

        def count(block: NDArray[np.uint8], local: NDArray[np.int64], out: NDArray | None = None) -> NDArray:
            return sum_packed_ranges(combine_channels(block, channels), local, out=out)

        count.adds_into_out = True  # type: ignore[attr-defined]
        return self.frames.sum_ranges(edges + self.offset, count, (self.height, self.width))

    def describe(self) -> dict[str, Any]:
        """Return the capture summary with the cubes, channels, frame range and references."""
        return {**super().describe(), "cubes": len(self.cubes), "first_cube": str(self.cubes[0]),
                "channels": self.config.channels, "start": self.offset,
                "references": [str(p) if p is not None else None for p in self.references]}


def _is_challenge_cube(path: Path) -> bool:
    """Whether the header of ``path`` declares a (T, H, W/8, 3) uint8 array (reads the header only)."""
    from photonpano.npy_header import check_npy

    try:
        shape, dtype, _ = check_npy(path, "source (spc-challenge)")
    except SourceError:
        return False
    return len(shape) == 4 and shape[3] == 3 and dtype == np.uint8


@hookimpl
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Register the ``spc-challenge`` source."""
    return [SpcChallengeConfig]


@hookimpl(tryfirst=True)
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Claim an ``.npy`` cube of the challenge layout, or a folder whose first ``.npy`` file is one.

    Called before ``npy-cube`` (which claims any ``.npy`` file); only the header is read.
    """
    if path.is_file() and path.suffix.lower() == ".npy":
        return {"plugin": "spc-challenge", "path": str(path)} if _is_challenge_cube(path) else None
    if path.is_dir():
        try:
            first = _cubes_of(path)[0][0]
        except SourceError:
            return None
        if _is_challenge_cube(first):
            return {"plugin": "spc-challenge", "path": str(path)}
    return None
