"""Detect flickering light from the photon counts: its frequency, depth and where it falls.

Mains-powered lamps flicker at twice the mains frequency (100 or 120 Hz), LED drivers at
hundreds of hertz; a camera at 100 kHz resolves every cycle. Flicker breaks the method's
brightness constancy. Over the *whole* field it is harmless (every locator is invariant
to a global gain), but a lamp lighting *part* of the scene changes the merged frames'
brightness there from one virtual exposure to the next, and the photons of its part
arrive mostly in the lamp's bright phases, so that part of a merged frame shows the
scene at a different time than the rest; registrations then disagree consistently and
the held-out evidence cannot see it (the paper's failure case, Sec. 6).

:func:`detect_flicker` measures it as a spectral analysis of the photon counts
(Welch-free: one windowed DFT per region, Harris, "On the use of windows for harmonic
analysis with the discrete Fourier transform", Proc. IEEE 66, 1978): the counts of a
contiguous stretch of the capture are summed in bins of a few binary frames over a
coarse grid of regions; the strongest common spectral peak between :data:`MIN_HZ` and
half the bin rate is the flicker frequency; each region's counts folded at that period
give its depth (1 - darkest phase / brightest phase). Camera motion moves texture across
the regions' borders, which modulates their counts far less than a lamp does, and is
slower than mains flicker for hand-held and vehicle-mounted cameras.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

if TYPE_CHECKING:
    from .stages import Compositor

__all__ = ["Flicker", "detect_flicker", "told_of_flicker", "MIN_HZ", "MIN_DEPTH"]

MIN_HZ = 80.0
"""Lowest frequency searched, in Hz (above camera shake; below the 100/120 Hz of mains lamps)."""

MIN_DEPTH = 0.15
"""A region whose counts dim by less than this share over a flicker period is steady."""

MIN_SIGNIFICANCE = 100.0
"""A region flickers only if its spectral power at the peak is this many times the median
power 3-5 frequency bins above it (photon noise and transients spread their power; a lamp
is a line, its first harmonic further up), ..."""

MIN_AMPLITUDE = 0.05
"""... and if the peak's amplitude is at least this share of the region's mean count (a lamp
dimming by 15 % modulates by about 7 %; camera shake by a few percent)."""

GRID = (3, 3)
"""Regions per side (rows, columns) of the frame the counts are summed over."""


@dataclass(frozen=True)
class Flicker:
    """Flicker found in a capture.

    Attributes:
        frequency_hz: flicker frequency in Hz (the lamp's brightness period, i.e. twice
            the mains frequency for a mains lamp).
        depth: (rows, cols) float64 per region of the frame (:data:`GRID`, row-major from
            the top left): 1 - darkest / brightest mean count over eighths of a flicker
            period (a lamp dimming to 10 % of its peak, depth 0.9, reads about 0.8), 0
            where the region shows no spectral line at the frequency.
        modulation: the spectral peak's amplitude over the mean count (whole frame).
        frames: (start, stop) binary frames analysed.
        frame_rate_hz: the capture's binary frames per second.
    """

    frequency_hz: float
    depth: NDArray[np.float64]
    modulation: float
    frames: tuple[int, int]
    frame_rate_hz: float

    @property
    def period_frames(self) -> float:
        """The flicker period in binary frames."""
        return self.frame_rate_hz / self.frequency_hz

    @property
    def flickering(self) -> NDArray[np.bool_]:
        """(rows, cols) bool regions that dim by at least :data:`MIN_DEPTH` over a period."""
        return self.depth >= MIN_DEPTH

    @property
    def partial(self) -> bool:
        """Whether the flicker lights only part of the field (some regions steady, or depths differing by half)."""
        lit = self.depth[self.flickering]
        return bool(len(lit)) and (len(lit) < self.depth.size or float(lit.min()) < 0.5 * float(lit.max()))

    def spans_whole_periods(self, frames: int) -> bool:
        """Whether ``frames`` binary frames hold a whole number (>= 1) of flicker periods (within 1 %)."""
        periods = frames / self.period_frames
        return periods >= 0.99 and abs(periods - round(periods)) < 0.01

    def record(self) -> dict[str, Any]:
        """The ``run.json`` entry: frequency, per-region depths, affected regions, partial or not."""
        return {"frequency_hz": round(self.frequency_hz, 2), "depth": np.round(self.depth, 3).tolist(),
                "regions": [f"{_ROW[r]}-{_COL[c]}" for r, c in zip(*np.nonzero(self.flickering))],
                "partial": self.partial, "modulation": round(self.modulation, 4),
                "period_frames": round(self.period_frames, 2), "frames": list(self.frames)}


_ROW = ("top", "middle", "bottom")
_COL = ("left", "centre", "right")


def detect_flicker(source: Any, *, frames: int = 8000, bin_frames: int = 10,
                   chunk: int = 64) -> Flicker | None:
    """Look for flickering light in the middle ``frames`` binary frames of a capture.

    Args:
        source: the capture (a :class:`~photonpano.stages.PhotonSource`; its
            ``sum_ranges`` gives the counts, ``frame_rate_hz`` the time base).
        frames: binary frames analysed (contiguous, from the middle of the capture);
            their span sets the frequency resolution (8000 frames at 100 kHz: 12.5 Hz,
            refined by folding).
        bin_frames: binary frames summed per sample (the bin rate ``frame_rate_hz /
            bin_frames`` must exceed twice the flicker frequency).
        chunk: samples read per call of ``sum_ranges`` (bounds memory: chunk frames of
            the sensor's size as uint16).

    Returns:
        The :class:`Flicker` if some region dims by at least :data:`MIN_DEPTH` at a
        frequency between :data:`MIN_HZ` and the bin rate's Nyquist frequency, else None
        (also for captures too short to hold 4 periods of :data:`MIN_HZ`, or too fast a
        flicker for the frame rate).
    """
    rate = float(source.frame_rate_hz) / bin_frames
    n = min(int(source.n_frames), frames)
    samples = n // bin_frames
    if rate <= 2 * MIN_HZ or samples * bin_frames / float(source.frame_rate_hz) < 4 / MIN_HZ:
        return None
    start = (int(source.n_frames) - samples * bin_frames) // 2
    counts = _region_counts(source, start, samples, bin_frames, chunk)  # (samples, rows * cols)
    mean = counts.mean(axis=0)
    if not np.all(mean > 0):
        return None
    relative = counts / mean - 1.0
    # high-pass: camera motion brings new scene content into a region slowly; its drift
    # would leak into the band through the window (moving mean over two periods of MIN_HZ/2)
    span = max(3, int(round(4 * rate / MIN_HZ)))
    relative = relative - uniform_filter1d(relative, span, axis=0, mode="nearest")
    window = np.hanning(samples)[:, None]
    spectrum = np.abs(np.fft.rfft(relative * window, axis=0)) / (window.sum() / 2)
    frequencies = np.fft.rfftfreq(samples, 1.0 / rate)
    band = (frequencies >= MIN_HZ) & (frequencies < rate / 2 * 0.9)
    if not band.any() or np.flatnonzero(band)[-1] + 6 > len(frequencies):
        return None
    power = (spectrum ** 2).sum(axis=1)
    peak = int(np.flatnonzero(band)[np.argmax(power[band])])
    # a lamp is a strong spectral line in the regions it lights: far above the frequencies
    # just above it (below lie the shake and the drift the high-pass left). Shake modulates
    # a region's counts by a few percent at most (measured: <= 3 % for 5 px at 30-45 Hz in
    # regions of 32x64 pixels); an object crossing a region is a transient whose power
    # spreads over neighbouring frequencies.
    near = np.arange(peak + 3, min(len(frequencies), peak + 6))
    significant = ((spectrum[peak] ** 2 >= MIN_SIGNIFICANCE * np.median(spectrum[near] ** 2, axis=0))
                   & (spectrum[peak] >= MIN_AMPLITUDE))
    if not significant.any():
        return None
    frequency = max(MIN_HZ, _refine(relative * window, rate, frequencies[peak], frequencies[1]))
    depth = np.where(significant, _folded_depth(counts, rate, frequency), 0.0).reshape(GRID)
    if not np.any(depth >= MIN_DEPTH):
        return None
    whole = counts.sum(axis=1)
    modulation = float(np.abs(np.fft.rfft((whole / whole.mean() - 1) * window[:, 0]))[peak] / (window.sum() / 2))
    return Flicker(frequency, depth, modulation, (start, start + samples * bin_frames),
                   float(source.frame_rate_hz))


def _region_counts(source: Any, start: int, samples: int, bin_frames: int, chunk: int) -> NDArray[np.float64]:
    """(samples, rows * cols) float64 detections per region and bin of ``bin_frames`` frames."""
    rows, cols = GRID
    h, w = int(source.height), int(source.width)
    ys = np.linspace(0, h, rows + 1).astype(int)
    xs = np.linspace(0, w, cols + 1).astype(int)
    out = np.empty((samples, rows * cols), np.float64)
    for first in range(0, samples, chunk):
        last = min(samples, first + chunk)
        edges = start + np.arange(first, last + 1, dtype=np.int64) * bin_frames
        sums = source.sum_ranges(edges)  # (k, h, w) uint16 counts (float32 for intensity sources)
        accumulator = np.float64 if sums.dtype.kind == "f" else np.int64
        rows_summed = [sums[:, y0:y1].sum(axis=1, dtype=accumulator) for y0, y1 in zip(ys[:-1], ys[1:])]
        out[first:last] = np.stack([[band[:, x0:x1].sum(axis=1) for x0, x1 in zip(xs[:-1], xs[1:])]
                                    for band in rows_summed]).transpose(2, 0, 1).reshape(len(sums), -1)
    return out


def _refine(relative: NDArray[np.float64], rate: float, coarse: float, step: float) -> float:
    """The frequency within one DFT bin of ``coarse`` with the most power in the (windowed) ``relative`` counts."""
    candidates = coarse + np.linspace(-step, step, 41)
    t = np.arange(len(relative)) / rate
    best, best_power = coarse, -1.0
    for f in candidates:
        phasor = np.exp(-2j * np.pi * f * t)
        power = float((np.abs(phasor @ relative) ** 2).sum())
        if power > best_power:
            best, best_power = float(f), power
    return best


def _folded_depth(counts: NDArray[np.float64], rate: float, frequency: float, phases: int = 8) -> NDArray[np.float64]:
    """(regions,) 1 - darkest / brightest mean count over ``phases`` bins of the flicker period."""
    phase = ((np.arange(len(counts)) / rate * frequency) % 1.0 * phases).astype(int)
    means = np.stack([counts[phase == k].mean(axis=0) if np.any(phase == k) else np.full(counts.shape[1], np.nan)
                      for k in range(phases)])
    brightest, darkest = np.nanmax(means, axis=0), np.nanmin(means, axis=0)
    return np.where(brightest > 0, 1.0 - darkest / np.maximum(brightest, 1e-12), 0.0)


def told_of_flicker(build: Callable[[], Compositor], flicker: Flicker | None) -> Callable[[], Compositor]:
    """``build``, its compositors told of the capture's flicker (:meth:`~photonpano.stages.Compositor.expect_flicker`).

    Args:
        build: builds a compositor.
        flicker: the :class:`Flicker` found in the capture, or None (``build`` is returned as it is).
    """
    if flicker is None:
        return build

    def make() -> Compositor:
        compositor = build()
        compositor.expect_flicker(flicker.period_frames)
        return compositor

    return make
