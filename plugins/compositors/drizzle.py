"""Compositor ``drizzle``: forward splats of frame pixel centres, flux MLE per canvas pixel.

Every binary frame is a fresh set of point samples of the scene at a new sub-pixel
phase. Drizzle (Fruchter and Hook, "Drizzle: a method for the linear reconstruction of
undersampled images", PASP 114, 2002) keeps that phase: each frame pixel's centre is
mapped forward onto the canvas by its homography and its detections are dropped there
with a small kernel (a point, a square of side ``pixfrac`` frame pixels, or a Gaussian
of that FWHM); the number of frames behind each drop is dropped with the same weights
(exposure weighting), and the flux per canvas pixel is the MLE of paper Eq. (3),
``phi = -ln(1 - S / N) / tau`` (the mean for intensity sources). Bilinear backward warps
(``flux-canvas``) blur by about a frame pixel instead, so at ``scale: 2`` drizzle
resolves detail finer than the frame pixels where ``flux-canvas`` cannot.

Small drops gather few photons per canvas pixel: with ``noise_adaptive`` (the default,
photon sources) the fine estimate is kept as far as its detail stands above its photon
noise. By default (``restoration: wiener``, :mod:`._restore`) a sliding-DCT Wiener
filter denoises the fine drops and inverts their blur (issue 27, the 15 suite photographs
with estimated motion: +2.7 to +6.8 dB above the bilinear merge with the true motion at
``scale: 2`` on an undersampled capture, +3.6 to +11.4 dB at ``scale: 1``);
``restoration: blend`` blends each canvas pixel with a wide drop instead
(:mod:`._adaptive`, a local Wiener weight from the binomial statistics of the counts),
which the measurements below describe.
Measured on a capture whose sensor undersamples the scene 2x, with the true motion at
``scale: 2``: plain drizzle is 3.4 dB above the bilinear merge where the capture covers
the canvas well but 2.3 dB below it where few frames looked (the panorama's ends);
noise-adaptive drizzle is above it everywhere (see docs/performance.md).

Canvas pixels no drop reached are NaN: at ``scale > 1`` with a ``point`` kernel the
motion must dither the frames over the finer grid (as the sub-pixel jitter of a
hand-held or vibrating camera does); a larger ``pixfrac`` fills gaps at the cost of
resolution.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import geometry, hookimpl
from photonpano.compose import Canvas, Panorama
from photonpano.robust_merge import (
    DEFAULT_EXPOSURES,
    exposure_bounds,
    feed_exposures,
    join_exposures,
    keep_exposures,
    robust_rejection,
    whole_period_frames,
)
from photonpano.stages import Compositor, CompositorConfig, PhotonSource
from pydantic import Field

from ._adaptive import DETAIL_GAIN
from ._restore import DEBLUR, deblur_for_scale

__all__ = ["DrizzleConfig", "Drizzle"]


class DrizzleConfig(CompositorConfig):
    """Forward splats of frame pixel centres (drizzle), exposure-weighted flux MLE per canvas pixel."""

    plugin: Literal["drizzle"] = "drizzle"
    kernel: Literal["point", "square", "gaussian"] = "square"
    """Drop shape: the canvas pixel the centre lands in; an axis-aligned square of side
    ``pixfrac`` frame pixels spread by overlap area; or a Gaussian of FWHM ``pixfrac``
    frame pixels."""
    pixfrac: Annotated[float, Field(gt=0, le=2)] | None = None
    """Drop size in frame pixels (square side or Gaussian FWHM; unused by ``point``);
    None: one canvas pixel, ``1 / scale``. Smaller is sharper and noisier and needs more
    sub-pixel dither to cover the canvas."""
    noise_adaptive: bool = True
    """Estimate each canvas pixel from the fine drops as far as their detail stands above
    their photon noise (binary sources; intensity sources are unaffected): see
    ``restoration``. False: plain drizzle."""
    restoration: Literal["wiener", "blend"] = "wiener"
    """How ``noise_adaptive`` does it: ``wiener``, a sliding-DCT Wiener filter that
    denoises the fine drops and inverts their blur (:mod:`._restore`); ``blend``, a
    per-pixel blend of the fine drops with a wide drop (:mod:`._adaptive`; 2.2 dB lower at
    ``scale: 2`` on an undersampled capture, 4 dB lower at ``scale: 1``)."""
    deblur: Annotated[float, Field(ge=0, lt=0.25)] | None = None
    """Per-axis weight ``a`` of the ``[a, 1 - 2a, a]`` canvas blur that ``wiener``
    inverts (a square drop of one canvas pixel and the sensor's interpolation of the
    scene; 0: denoise only). None: by ``scale``, 1/6 at ``scale: 1`` and 0.2 from
    ``scale: 2`` on, where the sensor's blur is on the canvas's scale too
    (``._restore.deblur_for_scale``: +0.16 dB on average at ``scale: 2`` on an
    undersampled capture), and along each axis less where the drops landed near the
    canvas pixels' centres rather than at every sub-pixel phase (a camera that does not
    move: ``Drizzle.blur_weights``). A value set here is inverted as set."""
    wide_px: Annotated[float, Field(gt=0, le=8)] = 2.0
    """Half-width in frame pixels of the tent that makes the wide estimate of
    ``noise_adaptive``."""
    robust: bool = True
    """Robust merge: keep ``robust_exposures`` runs of frames apart and leave out those that
    disagree with the static scene at a canvas pixel (a moving object; see
    ``photonpano.robust_merge``); the left-out regions go to ``moving.png``. On static
    captures it changes the panorama by less than 0.01 dB (docs/real_scenes.md). The
    colour panorama (``colour_panorama``) leaves out the same exposures in every plane."""
    robust_exposures: Annotated[int, Field(ge=3, le=64)] = DEFAULT_EXPOSURES
    """Virtual exposures the robust merge compares (memory: that many canvases; under a
    flickering lamp, runs of whole periods: up to twice as many)."""
    detail_gain: Annotated[float, Field(gt=0, le=100)] = DETAIL_GAIN
    """Factor on the local detail variance in the weight of ``noise_adaptive`` (1: Lee's
    local Wiener weight; larger keeps more of the fine drops at edges)."""

    def build(self) -> Drizzle:
        """Return the compositor."""
        return Drizzle(self.scale, self.kernel, self.pixfrac or 1.0 / self.scale,
                       wide_px=self.wide_px if self.noise_adaptive else None, detail_gain=self.detail_gain,
                       exposures=self.robust_exposures if self.robust else None,
                       restoration=self.restoration,
                       deblur=deblur_for_scale(self.scale) if self.deblur is None else self.deblur,
                       adapt_deblur=self.deblur is None)


class Drizzle(Compositor):
    """The ``drizzle`` compositor (see the module docstring).

    Args:
        scale: super-resolution scale (canvas pixels per frame pixel).
        kernel: ``"point"``, ``"square"`` or ``"gaussian"``.
        pixfrac: drop size in frame pixels (square side or Gaussian FWHM).
        wide_px: half-width in frame pixels of the wide estimate that noise-adaptive
            drizzle blends in (:func:`._adaptive.blend_sums`); None: plain drizzle.
        detail_gain: factor on the detail variance in that blend's weight.
        restoration: ``"blend"`` (:func:`._adaptive.blend_sums`) or ``"wiener"``
            (:func:`._restore.restore_sums`): how the fine drops are made noise-adaptive.
        deblur: the blur weight ``wiener`` inverts (:func:`._restore.dct_wiener`) where
            the drops land at every sub-pixel phase alike.
        adapt_deblur: adapt ``deblur`` per axis to the phases the drops landed at
            (:meth:`blur_weights`; square drops only); False: ``deblur`` as given.
        exposures: virtual exposures kept apart for the robust merge
            (:func:`photonpano.robust_merge.robust_combine`, fed through :meth:`feed_ranges`;
            a plain :meth:`feed` goes to the first); None or 1: every photon merged.
    """

    def __init__(self, scale: float = 1.0, kernel: str = "square", pixfrac: float = 1.0,
                 wide_px: float | None = None, detail_gain: float = 1.0, exposures: int | None = None,
                 restoration: str = "blend", deblur: float = DEBLUR, adapt_deblur: bool = True) -> None:
        """Create an unprepared compositor.

        Raises:
            ValueError: for an unknown ``kernel`` or ``restoration``.
        """
        from . import _splat

        if restoration not in ("blend", "wiener"):
            raise ValueError(f"Drizzle: restoration must be 'blend' or 'wiener', got {restoration!r}")
        if kernel not in ("point", "square", "gaussian"):
            raise ValueError(f"Drizzle: kernel must be 'point', 'square' or 'gaussian', got {kernel!r}")
        self.restoration, self.deblur, self.adapt_deblur = restoration, deblur, adapt_deblur
        self._phases = _DropPhases()

        self.scale, self.kernel, self.pixfrac, self.wide_px = scale, kernel, pixfrac, wide_px
        self.detail_gain = detail_gain
        self.exposures = max(1, int(exposures or 1))
        self.period_frames: float | None = None  # exposures of whole flicker periods (expect_flicker)
        self._splat = {"point": _splat.splat_point, "square": _splat.splat_square,
                       "gaussian": _splat.splat_gaussian}[kernel]

    def expect_flicker(self, period_frames: float) -> None:
        """Cut the virtual exposures at whole flicker periods (see :meth:`Compositor.expect_flicker`)."""
        self.period_frames = float(period_frames)

    def prepare(self, canvas: Canvas, source: PhotonSource) -> None:
        """Start empty sums on ``canvas`` (see :meth:`Compositor.prepare`)."""
        self._canvas, self._source = canvas, source
        self._bounds = exposure_bounds(len(canvas.homographies), self.exposures, getattr(source, "frame_step", 1),
                                       self.period_frames)
        self._acc = np.zeros((*canvas.shape, 2), np.float32)  # sums and frames, interleaved
        # the robust merge's virtual exposures (the first is ``_acc``), made when first fed:
        # a fork holds the few its run of frames spans
        self._accs: list[NDArray[np.float32] | None] = [self._acc] + [None] * (len(self._bounds) - 2)

    def feed(self, counts: NDArray, n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Splat a sub-batch (see :meth:`Compositor.feed`)."""
        self._splat_into(self._acc, counts, n_frames, homographies, weights)

    def _splat_into(self, acc: NDArray[np.float32], counts: NDArray, n_frames: NDArray[np.int64],
                    homographies: NDArray[np.float64], weights: NDArray[np.float32] | None = None) -> None:
        """Splat a sub-batch into ``acc``, (Hc, Wc, 2) float32 interleaved sums and frames."""
        counts = np.ascontiguousarray(counts)
        if counts.dtype not in (np.uint16, np.float32):
            counts = counts.astype(np.float32)
        if weights is None:
            weights = np.ones(counts.shape[1:], np.float32)
        homographies = np.asarray(homographies, np.float64)
        finite = np.isfinite(homographies).all(axis=(1, 2))  # the compiled kernels assume finite numbers
        if not finite.all():
            counts, n_frames, homographies = counts[finite], np.asarray(n_frames)[finite], homographies[finite]
        args = (counts, np.asarray(n_frames, np.int64), np.ascontiguousarray(homographies, np.float64),
                np.ascontiguousarray(weights, np.float32), acc)
        if self.kernel == "square" and len(homographies):
            self._phases.add(homographies, args[1], counts.shape[1:], self._side())
        self._splat(*args) if self.kernel == "point" else self._splat(*args, float(self.pixfrac))

    def frame_breaks(self, n_frames: int, frame_step: int = 1) -> NDArray[np.int64] | None:
        """The virtual exposures' boundaries (see :meth:`Compositor.frame_breaks`); None without the robust merge."""
        return self._bounds[1:-1] if self.exposures > 1 else None

    def feed_ranges(self, edges: NDArray[np.int64], counts: NDArray, homographies: NDArray[np.float64],
                    weights: NDArray[np.float32] | None = None) -> None:
        """Splat a sub-batch into its virtual exposures (see :meth:`Compositor.feed_ranges`).

        Args:
            edges: (B + 1,) int64 frame-range edges of the count images.
            counts: (B, H, W) summed frames.
            homographies: (B, 3, 3) float64 frame-to-canvas homographies.
            weights: optional (H, W) float32 per-pixel weights, as :meth:`feed`'s.
        """
        if self.exposures == 1:
            return self.feed(counts, np.diff(np.asarray(edges, np.int64)).astype(np.int64), homographies, weights)
        feed_exposures(self._accs, lambda: np.zeros_like(self._acc),
                       lambda acc, c, n, h: self._splat_into(acc, c, n, h, weights), edges, counts, homographies,
                       self._bounds)

    def fork(self) -> Drizzle:
        """An empty copy on the same canvas (see :meth:`Compositor.fork`)."""
        other = Drizzle(self.scale, self.kernel, self.pixfrac, self.wide_px, self.detail_gain, self.exposures,
                        self.restoration, self.deblur, self.adapt_deblur)
        other.period_frames = self.period_frames
        other.prepare(self._canvas, self._source)
        return other

    def join(self, other: Compositor) -> None:
        """Add a fork's sums (see :meth:`Compositor.join`)."""
        if not isinstance(other, Drizzle):
            raise TypeError(f"Drizzle.join: expected a fork of this compositor, got {type(other).__name__}")
        join_exposures(self._accs, other._accs, np.ndarray.__iadd__)
        self._phases.join(other._phases)

    def _exposures(self) -> NDArray[np.float32]:
        """(K', Hc, Wc, 2) float32 sums and frames of the virtual exposures fed so far."""
        return np.stack([a for a in self._accs if a is not None])

    def rejection(self) -> NDArray[np.bool_] | None:
        """(K', Hc, Wc) bool: where each virtual exposure fed so far disagrees with the static scene.

        :func:`photonpano.robust_merge.robust_rejection` of this compositor's exposures
        (K' of the ``exposures``, those fed); None without the robust merge. Another
        drizzle fed the same frames can :meth:`finish` with it (the colour planes,
        :class:`.colour.LumaGuided`).
        """
        return None if self.exposures == 1 else self._reject(self._exposures())

    def _reject(self, stacked: NDArray[np.float32]) -> NDArray[np.bool_]:
        """:meth:`rejection` of the stacked exposures."""
        return robust_rejection(stacked[..., 0], stacked[..., 1], scale=self.scale,
                                binary=getattr(self._source, "kind", "binary") == "binary",
                                exposure_frames=whole_period_frames(self._bounds, self._accs, self.period_frames))

    def _side(self) -> float:
        """A square drop's side in canvas pixels (``pixfrac`` frame pixels)."""
        return self.pixfrac * self.scale

    def blur_weights(self) -> tuple[float, float]:
        """The ``(horizontal, vertical)`` weights ``a`` of the ``[a, 1 - 2a, a]`` blur the restoration inverts.

        ``deblur`` was measured on moving cameras, whose drops land at every sub-pixel
        phase alike. A camera that does not move drops every frame at one phase, and there
        the blur is the drops' own: a square drop of side ``s <= 1`` canvas pixels whose
        centre lands ``d`` pixels from a canvas pixel's centre spills ``max(0, |d| + s/2 -
        1/2) / s`` of itself into the neighbouring pixel, which at every phase alike
        averages ``s / 4``. Per axis, the weight is ``deblur`` times ``w + (1 - w) r``: ``r``
        the drops' mean spill over ``s / 4`` (at most 1), ``w`` the span of the frames'
        positions along the axis in canvas pixels (at most 1; the median over a grid of
        frame pixels, :class:`_DropPhases`). Inverting a moving camera's blur on a camera
        that does not move cost 14 dB (20 000 frames over the evaluation suite's
        dandelions at flux 0.5, drops 0.05 px from the pixel centres: 34.2 dB, adapted
        49.7 dB, ``flux-canvas`` 47.9 dB); the span keeps a camera that moves a pixel or
        more at ``deblur`` whatever its phases (the city under a 0.6 px vibration: the spill
        alone 0.4 dB under ``deblur``; docs/accuracy.md).

        Returns:
            ``(horizontal, vertical)`` weights in ``[0, deblur]``; ``(deblur, deblur)``
            without ``adapt_deblur``, for other kernels, drops larger than a canvas pixel,
            or before any frame.
        """
        side = self._side()
        if not self.adapt_deblur or self.kernel != "square" or side > 1 + 1e-6 or self._phases.frames <= 0:
            return self.deblur, self.deblur
        across, down = self.deblur * self._phases.blur_share(side)
        return float(across), float(down)

    def finish(self, rejected: NDArray[np.bool_] | None = None) -> Panorama:
        """The flux MLE per canvas pixel (see :meth:`Compositor.finish`); robust: the exposures that agree.

        Args:
            rejected: with the robust merge, (K', Hc, Wc) bool exposures to leave out (a
                :meth:`rejection`, possibly another drizzle's fed the same frames); None:
                this compositor's own :meth:`rejection`.
        """
        from photonpano.intensity import estimate_radiance

        moving = None
        if self.exposures > 1:
            stacked = self._exposures()
            if rejected is None:
                rejected = self._reject(stacked)
            sums, frames, moving = keep_exposures(stacked[..., 0], stacked[..., 1], rejected)
        else:
            sums, frames = np.ascontiguousarray(self._acc[..., 0]), np.ascontiguousarray(self._acc[..., 1])
        if self.wide_px is not None and getattr(self._source, "kind", "binary") == "binary":
            from ._adaptive import blend_sums, drop_sharpness
            from ._restore import restore_sums

            sharpness = drop_sharpness(self.kernel, self._side())
            if self.restoration == "wiener":
                sums = restore_sums(sums, frames, self.scale, self.wide_px, sharpness, self.blur_weights())
            else:
                sums = blend_sums(sums, frames, self.scale, self.wide_px, sharpness, self.detail_gain)
        flux = estimate_radiance(self._source, sums, frames)
        return Panorama(flux=flux, frames=frames, homographies=self._canvas.homographies, moving=moving)


SPILL_GRID = 4
"""Frame pixel centres per axis (a grid over the frame) at which :class:`_DropPhases` reads the drops."""


class _DropPhases:
    """Where a drizzle's drops landed, for :meth:`Drizzle.blur_weights`: their spill and the frames' span.

    Read at a :data:`SPILL_GRID` square grid of frame pixel centres: per axis, the
    binary frames behind the drops and the share of each drop spilt into the next canvas
    pixel, summed, and each grid point's lowest and highest canvas position.
    """

    def __init__(self) -> None:
        """No drops yet."""
        self.frames = 0.0
        self.spill = np.zeros(2)
        self.low = np.full((SPILL_GRID ** 2, 2), np.inf)
        self.high = np.full((SPILL_GRID ** 2, 2), -np.inf)

    def add(self, homographies: NDArray[np.float64], n_frames: NDArray[np.int64], frame_shape: tuple[int, ...],
            side: float) -> None:
        """Add a sub-batch.

        Args:
            homographies: (B, 3, 3) float64 finite frame-to-canvas homographies (pixel centres at integers).
            n_frames: (B,) int64 binary frames behind each count image.
            frame_shape: ``(H, W)`` of the frames.
            side: the square drops' side in canvas pixels.
        """
        height, width = frame_shape
        with np.errstate(divide="ignore", invalid="ignore"):
            canvas = geometry.apply(homographies, geometry.pixel_grid(width, height, SPILL_GRID))  # (B, N, 2)
        seen = np.isfinite(canvas)
        spill = np.clip(np.abs(canvas - np.round(canvas)) + side / 2 - 0.5, 0.0, None) / side
        weights = np.asarray(n_frames, np.float64)
        self.frames += float(weights.sum())
        self.spill += weights @ np.where(seen, spill, 0.0).mean(axis=1)
        self.low = np.minimum(self.low, np.where(seen, canvas, np.inf).min(axis=0))
        self.high = np.maximum(self.high, np.where(seen, canvas, -np.inf).max(axis=0))

    def join(self, other: _DropPhases) -> None:
        """Add another's drops (a fork's)."""
        self.frames += other.frames
        self.spill += other.spill
        self.low, self.high = np.minimum(self.low, other.low), np.maximum(self.high, other.high)

    def blur_share(self, side: float) -> NDArray[np.float64]:
        """(2,) float64 per axis ``w + (1 - w) r`` in [0, 1] (:meth:`Drizzle.blur_weights`)."""
        spilt = np.clip(self.spill / max(self.frames, 1e-300) / (side / 4), 0.0, 1.0)
        with np.errstate(invalid="ignore"):
            span = np.nan_to_num(np.median(self.high - self.low, axis=0), posinf=1.0, neginf=0.0)
        moved = np.clip(span, 0.0, 1.0)
        return moved + (1 - moved) * spilt


@hookimpl
def photonpano_register_compositors() -> list[type[CompositorConfig]]:
    """Register the ``drizzle`` compositor."""
    return [DrizzleConfig]
