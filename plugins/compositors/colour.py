"""Colour compositors for colour-filtered sensors: demosaic through motion, and its baselines.

A colour-filtered SPAD (the SwissSPAD2 colour half array: red, green or blue filters on
one pixel in four, on an irregular layout, ``cfa``) samples each colour on a sparse grid.
Three ways to a colour panorama, each wrapping compositors once per channel:

- :class:`LumaGuided`, **luminance-guided demosaic through motion** (the panorama
  stage's, see :mod:`._guided`): the colour planes merged as :class:`CfaChannels` does,
  a sharp luminance from every unfiltered photon, and per channel the plane's colour
  ratio to the luminance on that luminance;
- :class:`CfaChannels`, the **per-plane merge**: each detection is composited into its
  own colour plane at its estimated canvas position (channel c's compositor is fed the
  raw counts with per-pixel weight 1 behind filter c and 0 elsewhere), each plane on its
  own. With a splatting compositor (``drizzle``) the camera's sub-pixel motion moves the
  sparse grid of each colour over the canvas, so every canvas pixel of every plane is
  observed directly: Wronski et al., "Handheld multi-frame super-resolution", SIGGRAPH
  2019, which merges raw Bayer bursts the same way;
- :class:`FrameDemosaic`, the conventional **per-frame demosaic, then merge** baseline:
  each sub-batch's sparse plane c is interpolated to every frame pixel first (normalised
  convolution with a separable tent of half-width ``radius_px`` frame pixels: bilinear
  interpolation of a regular lattice of that spacing, generalised to the irregular
  layout), and the dense planes are then composited with the run's homographies.

:class:`ColourPanorama` is the panorama stage's compositor with ``colour_panorama: true``
(:meth:`~photonpano.stages.SourceConfig.panorama_compositor`): the spec's compositor on the
inpainted counts and :class:`LumaGuided` on the raw ones, from one read of the capture.

Registration never sees the colour (``sum_ranges`` inpaints the filtered pixels from their
unfiltered neighbours); these compositors read the raw counts with :meth:`read`
(``source.raw_sums``, geometry fixed by ``source.corrector.geometry``): the SwissSPAD
sources (``npy-cube``, ``swissspad-bin``) and ``simulate``, with ``cfa`` set. Every plane
leaves out the corrector's ``hot`` pixels, which in a run hold the hot and dead pixels
found in the capture too (:class:`~photonpano.inpainting.InpaintedSource`).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from photonpano.stages import Compositor

__all__ = ["CfaChannels", "LumaGuided", "FrameDemosaic", "ColourPanorama", "cfa_corrector"]

CHANNELS = ("R", "G", "B")


def cfa_corrector(source: Any, where: str = "colour compositor") -> Any:
    """The sensor corrector of a colour-filtered source (its ``cfa`` codes 0 R, 1 G, 2 B).

    Args:
        source: a capture with ``corrector`` (``cfa`` (H, W) int8 codes, ``hot`` (H, W)
            bool, ``geometry``) and ``raw_sums``, as the SwissSPAD sources and
            ``simulate`` with ``cfa`` have.
        where: the caller's name for the error message.

    Returns:
        ``source.corrector``.

    Raises:
        ValueError: if the source has no colour filter layout.
    """
    corrector = getattr(source, "corrector", None)
    cfa = getattr(corrector, "cfa", None)
    if cfa is None or not hasattr(source, "raw_sums") or not np.isin(cfa, [0, 1, 2]).any():
        raise ValueError(f"{where}: the source has no colour filter layout (set cfa)")
    return corrector


class _PerChannel(Compositor):
    """Three compositors of one kind, one per colour channel; :meth:`finish` stacks them."""

    def __init__(self, make: Callable[[], Compositor], corrector: Any = None) -> None:
        self._make, self._corrector = make, corrector
        self._parts = [make() for _ in CHANNELS]
        self.scale = self._parts[0].scale

    def prepare(self, canvas: Any, source: Any) -> None:
        """Prepare each channel's compositor on ``canvas`` (see :meth:`Compositor.prepare`).

        Raises:
            ValueError: if neither the constructor nor ``source`` gives a colour layout.
        """
        if self._corrector is None:
            self._corrector = cfa_corrector(source, type(self).__name__)
        cfa, hot = self._corrector.cfa, self._corrector.hot  # masks: 1 at the healthy pixels behind each filter
        self._masks = np.stack([(cfa == c) & ~hot for c in range(len(CHANNELS))]).astype(np.float32)
        self._canvas, self._source = canvas, source
        for part in self._parts:
            part.prepare(canvas, source)

    def read(self, source: Any, edges: NDArray[np.int64]) -> NDArray:
        """(B, H, W) uint16 raw counts: sensor geometry fixed, filtered pixels kept."""
        return self._corrector.geometry(source.raw_sums(edges))

    def expect_flicker(self, period_frames: float) -> None:
        """Tell every channel's compositor (see :meth:`Compositor.expect_flicker`)."""
        for part in self._compositors():
            part.expect_flicker(period_frames)

    def _compositors(self) -> list[Compositor]:
        """Every compositor this one feeds."""
        return list(self._parts)

    def frame_breaks(self, n_frames: int, frame_step: int = 1) -> NDArray[np.int64] | None:
        """The channel compositors' (see :meth:`Compositor.frame_breaks`): the same sub-batches as the panorama's."""
        return self._parts[0].frame_breaks(n_frames, frame_step)

    def fork(self) -> _PerChannel | None:
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

    def finish(self, rejected: NDArray[np.bool_] | None = None) -> Any:
        """The colour :class:`~photonpano.compose.Panorama`.

        Its flux is (Hc, Wc, 3) float32 in photons/s behind the R, G, B filters (NaN
        where a channel saw nothing), its frames (Hc, Wc, 3) float32. ``rejected``: the
        virtual exposures each channel's drizzle leaves out (:meth:`.drizzle.Drizzle.finish`).
        """
        from photonpano.compose import Panorama

        panos = [part.finish() if rejected is None else part.finish(rejected) for part in self._parts]  # type: ignore[call-arg]
        return Panorama(flux=np.stack([p.flux for p in panos], axis=-1),
                        frames=np.stack([p.frames for p in panos], axis=-1),
                        homographies=panos[0].homographies)


class CfaChannels(_PerChannel):
    """Demosaic through motion: the R, G and B planes, each from the pixels behind its filter.

    Channel c's compositor is fed the raw counts with per-pixel weight 1 behind filter c
    and 0 elsewhere (and at hot pixels), so each detection lands in its own colour plane
    at its estimated canvas position (see the module docstring; with ``drizzle`` the
    motion fills every plane at every canvas pixel).

    Args:
        make: builds one (unprepared) compositor per channel, e.g. a compositor
            config's ``build``.
        corrector: the source's sensor corrector (``cfa`` (H, W) int8 codes 0 R, 1 G,
            2 B; ``hot`` (H, W) bool pixels to drop; ``geometry``); None: taken from the
            source in :meth:`prepare`.
    """

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Feed each channel the pixels behind its filter (times ``weights`` if given)."""
        for part, mask in zip(self._parts, self._masks):
            part.feed(counts, n_frames, homographies, mask if weights is None else mask * weights)


class FrameDemosaic(_PerChannel):
    """Baseline: demosaic each sub-batch of frames by interpolation, then merge each plane.

    For colour c with mask ``m_c`` (H, W) and a sub-batch's counts ``S`` (H, W), the dense
    plane is ``K * (m_c S) / K * m_c`` (normalised convolution, ``K`` a separable tent
    ``max(0, 1 - |d| / radius_px)`` per axis: bilinear interpolation on a regular lattice
    of spacing ``radius_px``), defined where ``K * m_c > 0``; it is composited with weight
    1 there (times ``weights``) and 0 elsewhere.

    Args:
        make: builds one (unprepared) compositor per channel.
        corrector: as for :class:`CfaChannels`.
        radius_px: half-width of the tent in frame pixels (3: every pixel of the
            SwissSPAD2 layout has each colour within it).

    Raises:
        ValueError: if ``radius_px`` is not above 1.
    """

    def __init__(self, make: Callable[[], Compositor], corrector: Any = None, radius_px: float = 3.0) -> None:
        """Build the three channel compositors."""
        if not radius_px > 1:
            raise ValueError(f"FrameDemosaic: radius_px must be above 1 frame pixel, got {radius_px}")
        super().__init__(make, corrector)
        d = np.arange(-np.ceil(radius_px) + 1, np.ceil(radius_px))
        self._tent = np.maximum(0, 1 - np.abs(d) / radius_px).astype(np.float32)

    def prepare(self, canvas: Any, source: Any) -> None:
        """Prepare the channels and the interpolation's normalisers (see :meth:`Compositor.prepare`)."""
        super().prepare(canvas, source)
        dens = np.stack([self._filter(m) for m in self._masks])
        self._covered = (dens > 1e-6).astype(np.float32)
        self._inverse = np.where(dens > 1e-6, 1 / np.maximum(dens, 1e-6), 0).astype(np.float32)

    def _filter(self, image: NDArray[np.float32]) -> NDArray[np.float32]:
        import cv2

        return cv2.sepFilter2D(image, cv2.CV_32F, self._tent, self._tent, borderType=cv2.BORDER_CONSTANT)

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Interpolate each channel's sparse counts to every frame pixel, then composite them."""
        counts = np.asarray(counts, np.float32)
        for part, mask, inverse, covered in zip(self._parts, self._masks, self._inverse, self._covered):
            dense = np.stack([self._filter(frame * mask) for frame in counts]) * inverse
            part.feed(dense, n_frames, homographies, covered if weights is None else covered * weights)


class LumaGuided(_PerChannel):
    """Luminance-guided demosaic through motion: sharp detail from every photon, colour ratios from the planes.

    The planes are merged on their own as in :class:`CfaChannels` (plain ``drizzle``,
    square drops of one canvas pixel); a fourth ``drizzle`` with point drops
    (noise-adaptive blend) merges the luminance of every unfiltered pixel; :meth:`finish`
    combines them with :func:`._guided.guided_colour` (see :mod:`._guided`) and scales
    each pixel's colour by a fifth luminance merge (the default ``drizzle``, Wiener
    restored, :mod:`._restore`) over the fourth: guided colour ratios, the sharper
    luminance (docs/capture_formats.md).
    Fed the raw counts (:meth:`read`), like :class:`CfaChannels`.

    Args:
        scale: super-resolution scale (canvas pixels per frame pixel).
        corrector: as for :class:`CfaChannels`.
        sigma_px: the fine colour ratio's bilateral sigma in canvas pixels at scale 1 (times
            ``scale`` on a finer canvas; the wide ratio's 4 px and residual's 1 px scale too);
            None: :data:`._guided.CHROMA_SIGMA_PX`.
        exposures: virtual exposures of the robust merge (fed through :meth:`feed_ranges`):
            the exposures that the luminance's :meth:`.drizzle.Drizzle.rejection` leaves
            out at a canvas pixel are left out of the luminance and every plane there
            (a moving object's ghost); None or 1: every photon merged.

    Raises:
        ValueError: if ``scale`` or ``sigma_px`` is not above 0.
    """

    def __init__(self, scale: float = 1.0, corrector: Any = None, sigma_px: float | None = None,
                 exposures: int | None = None) -> None:
        """Build the three plane compositors and the luminance one."""
        from ._adaptive import DETAIL_GAIN
        from ._guided import CHROMA_SIGMA_PX
        from .drizzle import Drizzle

        sigma_px = CHROMA_SIGMA_PX if sigma_px is None else sigma_px
        if not (scale > 0 and sigma_px > 0):
            raise ValueError(f"LumaGuided: scale and sigma_px must be above 0, got {scale}, {sigma_px}")
        super().__init__(lambda: Drizzle(scale, "square", 1.0 / scale, exposures=exposures), corrector)
        self._luma = Drizzle(scale, "point", wide_px=2.0, detail_gain=DETAIL_GAIN, exposures=exposures)
        self._sharp = Drizzle(scale, "square", 1.0 / scale, wide_px=2.0, restoration="wiener", exposures=exposures)
        self.sigma_px = sigma_px

    def prepare(self, canvas: Any, source: Any) -> None:
        """Prepare the planes and the luminance (see :meth:`Compositor.prepare`).

        Raises:
            ValueError: if neither the constructor nor ``source`` gives a colour layout.
        """
        super().prepare(canvas, source)
        self._luma.prepare(canvas, source)
        self._sharp.prepare(canvas, source)
        self._unfiltered = ((self._corrector.cfa < 0) & ~self._corrector.hot).astype(np.float32)

    def _compositors(self) -> list[Compositor]:
        """The planes' and the two luminance compositors."""
        return [*self._parts, self._luma, self._sharp]

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Feed each plane the pixels behind its filter and the luminance the unfiltered ones."""
        for part, mask in zip(self._compositors(), [*self._masks, *[self._unfiltered] * 2]):
            part.feed(counts, n_frames, homographies, mask if weights is None else mask * weights)

    def feed_ranges(self, edges: NDArray[np.int64], counts: NDArray, homographies: NDArray[np.float64]) -> None:
        """Feed each plane and the luminance their pixels' counts, into their virtual exposures (``exposures``)."""
        for part, mask in zip(self._compositors(), [*self._masks, *[self._unfiltered] * 2]):
            part.feed_ranges(edges, counts, homographies, mask)  # type: ignore[call-arg]  # drizzles take weights

    def fork(self) -> LumaGuided | None:
        """An empty copy on the same canvas."""
        other = super().fork()
        if not isinstance(other, LumaGuided):
            return None
        other._luma, other._sharp = self._luma.fork(), self._sharp.fork()
        return other

    def join(self, other: Compositor) -> None:
        """Add a fork's planes and luminance.

        Raises:
            TypeError: if ``other`` is not a fork of a :class:`LumaGuided`.
        """
        if not isinstance(other, LumaGuided):
            raise TypeError(f"LumaGuided.join: expected a fork of this compositor, got {type(other).__name__}")
        super().join(other)
        self._luma.join(other._luma)
        self._sharp.join(other._sharp)

    def finish(self) -> Any:  # type: ignore[override]  # its own luminance decides what is rejected
        """The colour :class:`~photonpano.compose.Panorama` (flux (Hc, Wc, 3) float32 photons/s, R, G, B).

        Its ``frames`` are the planes' (Hc, Wc, 3) drop-weighted frames; with ``exposures``,
        the exposures the luminance's robust merge rejects are left out of every plane.
        """
        from ._adaptive import drop_sharpness
        from ._guided import RESIDUAL_SIGMA_PX, WIDE_SIGMA_PX, guided_colour

        rejected = self._luma.rejection()  # None without the robust merge
        planes = super().finish(rejected)
        luma, sharp = self._luma.finish(rejected).flux, self._sharp.finish(rejected).flux
        binary = getattr(self._source, "kind", "binary") == "binary"
        flux = guided_colour(luma, planes.flux, planes.frames, float(self._source.exposure_s),
                             sigma_px=self.sigma_px * self.scale, residual_px=RESIDUAL_SIGMA_PX * self.scale,
                             wide_px=WIDE_SIGMA_PX * self.scale, sharpness=drop_sharpness("square", 1.0), binary=binary)
        usable = np.isfinite(sharp) & np.isfinite(luma) & (luma > 0)
        ratio = np.where(usable, sharp / np.where(usable, luma, 1), np.float32(1)).astype(np.float32)
        return dataclasses.replace(planes, flux=flux * ratio[..., None])


class ColourPanorama(Compositor):
    """The panorama and its colour planes in one pass: the panorama stage's colour compositor.

    Feeds the spec's compositor the source's corrected counts (filtered pixels inpainted,
    what ``sum_ranges`` returns: the panorama is the one without colour) and a
    :class:`LumaGuided` at its scale the raw counts, from one read of each sub-batch.
    :meth:`finish` returns the panorama with ``colour`` set.

    Args:
        make: builds the spec's compositor (its config's ``build``).
    """

    def __init__(self, make: Callable[[], Compositor]) -> None:
        """Build the panorama's and the colour planes' compositors."""
        self._flux = make()
        self.scale = self._flux.scale
        self._colour = LumaGuided(self.scale, exposures=getattr(self._flux, "exposures", None))

    def prepare(self, canvas: Any, source: Any) -> None:
        """Prepare both on ``canvas`` (see :meth:`Compositor.prepare`).

        Raises:
            ValueError: if the source has no colour filter layout.
        """
        self._corrector = cfa_corrector(source, "colour_panorama")
        self._flux.prepare(canvas, source)
        self._colour.prepare(canvas, source)

    def read(self, source: Any, edges: NDArray[np.int64]) -> NDArray[np.uint16]:
        """(2, B, H, W) uint16: the corrected (inpainted) and the raw counts of ``edges``."""
        raw = source.raw_sums(edges)
        fixed = self._corrector.geometry(raw)
        out = np.empty((2, *fixed.shape), fixed.dtype)
        out[1] = fixed  # first: apply inpaints in place when the geometry is the identity
        out[0] = self._corrector.apply(raw, np.asarray(edges, np.int64))
        return out

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Feed the corrected counts to the panorama and the raw ones to the colour planes."""
        self._flux.feed(counts[0], n_frames, homographies, weights)
        self._colour.feed(counts[1], n_frames, homographies, weights)

    def expect_flicker(self, period_frames: float) -> None:
        """Tell the panorama's and the colour planes' compositors (see :meth:`Compositor.expect_flicker`)."""
        self._flux.expect_flicker(period_frames)
        self._colour.expect_flicker(period_frames)

    def frame_breaks(self, n_frames: int, frame_step: int = 1) -> NDArray[np.int64] | None:
        """The panorama compositor's (see :meth:`Compositor.frame_breaks`)."""
        return self._flux.frame_breaks(n_frames, frame_step)

    def feed_ranges(self, edges: NDArray[np.int64], counts: NDArray, homographies: NDArray[np.float64]) -> None:
        """The corrected counts to the panorama, the raw ones to the colour (robust alike), both with their frames."""
        self._flux.feed_ranges(edges, counts[0], homographies)
        self._colour.feed_ranges(edges, counts[1], homographies)

    def fork(self) -> ColourPanorama | None:
        """An empty copy on the same canvas, if both compositors fork."""
        flux, colour = self._flux.fork(), self._colour.fork()
        if flux is None or colour is None:
            return None
        other = copy.copy(self)
        other._flux, other._colour = flux, colour
        return other

    def join(self, other: Compositor) -> None:
        """Add a fork's sums."""
        self._flux.join(other._flux)
        self._colour.join(other._colour)

    def finish(self) -> Any:
        """The panorama (see :meth:`Compositor.finish`) with ``colour``: (Hc, Wc, 3) float32 R, G, B."""
        return dataclasses.replace(self._flux.finish(), colour=self._colour.finish().flux)
