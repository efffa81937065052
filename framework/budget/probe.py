"""Virtual exposures that adapt to the capture: ``group_size: auto``.

The paper fixes the group size m (250-750 binary frames at 100 kHz) and notes that it
must grow in the dark and shrink for fast motion (Sec. 4 and suppl. S.3). A user does
not know their photon rate or speed in advance, so :func:`probe_capture` measures both
from the capture in a cheap pre-pass, and :func:`choose_group_size` turns them into m:

- **light**: detections per pixel per binary frame ``p``, from the probe's photon
  counts; a group should gather about ``photons`` detections per pixel, so
  ``m_light = photons / p``.
- **motion**: the apparent speed in pixels per binary frame, from phase correlation
  of heavily binned sums of adjacent blocks of frames at a few places in the capture;
  a group should not smear the scene by more than ``blur_px``, so
  ``m_motion = blur_px / speed``.

- **vibration**: the period of the strongest periodic motion, from the spectrum of
  the velocity in consecutive blocks (:func:`find_vibration`); level 1 should sample it
  ``groups_per_period`` times, so ``m_vibration = period / groups_per_period``.

m is ``min(typical, m_motion)``, raised towards ``m_light`` in the dark (up to twice
the blur budget), and at most ``m_vibration``; any photon deficit left is made up at
level 1 by registering spatially binned merged frames
(:class:`~photonpano.schemes.check.PairCheck`, the ``binning`` of the plan). Explicit
integers bypass all of this.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from ..imaging import block_mean, phase_shift_correlation
from ..movers import shift_without_mover

__all__ = ["CaptureProbe", "GroupPlan", "probe_capture", "choose_group_size", "plan_group_size", "short_of_light",
           "whole_flicker_periods"]


@dataclass(frozen=True)
class CaptureProbe:
    """What the pre-pass measured.

    Attributes:
        photons_per_pixel_per_frame: mean detections per pixel per binary frame (None
            for intensity sources, which have no photon counts).
        speed_px_per_frame: apparent speed of the scene in frame pixels per binary frame
            (75th percentile over the probes), or None when no probe found structure.
        block_frames: frames summed per probe block.
        binning: pixels binned per side in the probe images.
        correlations: normalised cross-correlation of each probe pair after its shift
            (near 0 for a capture without a scene).
        vibration_period_frames: period of the strongest periodic motion, in binary
            frames, or None when none stands out (:func:`find_vibration`).
        vibration_px: amplitude of that motion in frame pixels (None with no vibration).
    """

    photons_per_pixel_per_frame: float | None
    speed_px_per_frame: float | None
    block_frames: int = 0
    binning: int = 1
    correlations: list[float] = field(default_factory=list)
    vibration_period_frames: float | None = None
    vibration_px: float | None = None


@dataclass(frozen=True)
class GroupPlan:
    """The group size chosen for a capture and why (recorded in ``run.json``).

    Attributes:
        group_size: binary frames per group m at level 1.
        binning: pixels per side binned for the level-1 fallback registration (1: none).
        photons_per_pixel_per_group: expected detections per pixel in a level-1 merged
            frame (None for intensity sources).
        speed_px_per_frame: the probe's speed estimate (None: unknown).
        blur_px: expected motion smear within a group, in pixels (None: unknown).
        reason: one line saying which limit set m.
        auto: True when m was chosen here, False for an explicit integer.
        probe: the pre-pass figures (None when no probe ran).
        flicker: the :class:`~photonpano.flicker.Flicker` found in the capture, or None.
        extra_levels: levels to add to the spec's, keeping the last level's keyframes as
            dense as planned after ``flicker`` lengthened the groups.
    """

    group_size: int
    binning: int = 1
    photons_per_pixel_per_group: float | None = None
    speed_px_per_frame: float | None = None
    blur_px: float | None = None
    reason: str = "set in the spec"
    auto: bool = False
    probe: CaptureProbe | None = None
    flicker: Any = None
    extra_levels: int = 0

    def record(self) -> dict[str, Any]:
        """Return the JSON-ready ``group_size`` entry of ``run.json`` (the flicker has its own entry)."""
        out = asdict(replace(self, flicker=None))
        del out["flicker"]
        if self.probe is not None:
            out["probe"] = {**asdict(self.probe),
                            "correlations": [round(c, 3) for c in self.probe.correlations]}
        return out


def probe_capture(source, *, probes: int = 8, min_photons: float = 20.0, min_block: int = 200,
                  min_correlation: float = 0.25) -> CaptureProbe:
    """Measure a capture's photon rate and apparent speed from a few blocks of frames.

    The photon rate is first taken from the middle 1000 frames (to choose L), then from
    every probed block. At ``probes`` places spread over the capture, two adjacent
    blocks of L binary frames are summed, binned to about 32 pixels on the short side,
    and their shift is found by phase correlation, checked against a crossing bright
    object by :func:`~photonpano.movers.shift_without_mover`; speed = shift / L. L is the larger
    of ``min_block`` and the length that gathers ``min_photons`` detections per binned
    pixel, and is divided by 4 (down to 8 frames) while fewer than half the probes
    correlate, for motion that moves the frame by more than the correlation can follow;
    the step where most probes correlated is kept. Cost: ``2 * probes * L``
    frames of :meth:`~photonpano.stages.PhotonSource.sum_ranges`.

    Args:
        source: the capture (binary or intensity).
        probes: number of places probed.
        min_photons: detections per binned pixel per block (binary sources).
        min_block: shortest block, in binary frames.
        min_correlation: a probe whose images correlate less after the shift found no
            structure (photon noise alone correlates near 0).

    Returns:
        The :class:`CaptureProbe`.
    """
    n = source.n_frames
    binning = max(1, min(source.height, source.width) // 32)
    binary = source.kind != "intensity"
    if n < 8:  # too short to probe; the resampler says what is wrong with it
        return CaptureProbe(None, None)
    p = None
    if binary:
        sample = source.sum_ranges(np.array([n // 2 - min(n // 2, 500), n // 2 + min(n - n // 2, 500)]))
        p = float(sample.mean()) / min(n, 1000)
    block = min_block
    if p:
        block = max(block, math.ceil(min_photons / (p * binning ** 2)))
    best: tuple[int, list[float], list[float], int] = (-1, [], [], 0)
    detections, counted = 0.0, 0
    while True:
        length = max(1, min(block, n // 2))
        centres = np.unique(np.linspace(length, n - length, probes).astype(np.int64))
        speeds, correlations = [], []
        for centre in centres:
            counts = source.sum_ranges(np.array([centre - length, centre, centre + length]))
            detections, counted = detections + float(counts.mean()) * 2, counted + 2 * length
            a, _ = block_mean(counts[0].astype(np.float32), binning)
            b, _ = block_mean(counts[1].astype(np.float32), binning)
            shift, cc = shift_without_mover(a, b, *phase_shift_correlation(a, b), min_correlation)
            correlations.append(cc)
            speeds.append(float(np.hypot(*shift)) * binning / length if cc >= min_correlation else np.nan)
        found = int(np.sum(np.isfinite(speeds)))
        if found > best[0]:
            best = (found, speeds, correlations, length)
        if found >= len(centres) / 2 or length <= 8:
            break
        block = length // 4
    _, speeds, correlations, length = best
    good = np.asarray(speeds)[np.isfinite(speeds)]
    speed = float(np.percentile(good, 75)) if len(good) >= max(1, len(speeds) // 2) else None
    if binary:  # the rate over every probed block, spread over the capture
        p = detections / counted
    found_vibration = find_vibration(source, length, binning, min_correlation=min_correlation)
    period, amplitude = found_vibration if found_vibration is not None else (None, None)
    return CaptureProbe(p, speed, length, binning, [float(c) for c in correlations], period, amplitude)


def find_vibration(source, length: int, binning: int, *, blocks: int = 48, min_amplitude_px: float = 1.0,
                   min_prominence: float = 6.0, min_correlation: float = 0.25) -> tuple[float, float] | None:
    """The strongest periodic motion of a capture (a vibrating mount, a hand's tremor), if one stands out.

    In the middle of the capture, up to ``blocks`` consecutive blocks of ``length``
    binary frames are summed and binned ``binning`` x ``binning``; the shift between
    each block and the next (phase correlation) is the velocity, one sample per block.
    With its mean and linear trend (a pan) removed, the power spectrum of the velocity
    (Hann window, both axes summed) has its strongest line at frequency ``f`` (at least
    two cycles in the window, so a slow drift does not count); it is a vibration if its
    power is ``min_prominence`` times the median of the other lines and its amplitude
    in position, velocity amplitude / (2 pi f), is at least ``min_amplitude_px``.
    Vibrations faster than one period per two blocks are not resolved (the blocks
    average them out). Cost: ``blocks * length`` frames of ``sum_ranges``.

    Args:
        source: the capture.
        length: frames per block (the probe's block length).
        binning: pixels binned per side (the probe's).
        blocks: most blocks summed.
        min_amplitude_px: smallest amplitude reported, in frame pixels.
        min_prominence: power of the line over the median power of the spectrum.
        min_correlation: a block pair correlating less is a gap (more than a quarter of
            gaps: nothing reported).

    Returns:
        ``(period in binary frames, amplitude in frame pixels)``, or None.
    """
    n = source.n_frames
    count = min(blocks, n // max(length, 1))
    if count < 16:
        return None
    start = (n - count * length) // 2
    sums = source.sum_ranges(start + length * np.arange(count + 1, dtype=np.int64))
    images = [block_mean(s.astype(np.float32), binning)[0] for s in sums]
    velocity = np.full((count - 1, 2), np.nan)
    for i in range(count - 1):
        shift, cc = phase_shift_correlation(images[i], images[i + 1])
        if cc >= min_correlation:
            velocity[i] = shift * binning / length
    good = np.isfinite(velocity[:, 0])
    if good.sum() < 0.75 * len(velocity):
        return None
    t = np.arange(len(velocity), dtype=np.float64)
    for axis in range(2):  # gaps bridged linearly, then the pan (mean and trend) removed
        v = np.interp(t, t[good], velocity[good, axis])
        velocity[:, axis] = v - np.polyval(np.polyfit(t, v, 1), t)
    window = np.hanning(len(velocity))
    spectrum = np.fft.rfft(velocity * window[:, None], axis=0)
    power = (np.abs(spectrum) ** 2).sum(axis=1)
    k = 2 + int(np.argmax(power[2:]))
    others = np.delete(power[1:], k - 1)
    if power[k] < min_prominence * max(float(np.median(others)), 1e-30):
        return None
    frequency = k / (len(velocity) * length)  # cycles per binary frame
    speed_amplitude = 2 * float(np.sqrt(power[k])) / window.sum()  # px per frame
    amplitude = speed_amplitude / (2 * np.pi * frequency)
    return (1.0 / frequency, amplitude) if amplitude >= min_amplitude_px else None


def choose_group_size(probe: CaptureProbe, n_frames: int, *, blur_px: float = 10.0, photons: float = 10.0,
                      typical: int = 500, min_groups: int = 5, max_binning: int = 8,
                      groups_per_period: int = 3) -> GroupPlan:
    """Turn a probe into a group size (and level-1 binning).

    Args:
        probe: the pre-pass figures.
        n_frames: binary frames in the capture.
        blur_px: largest motion smear wanted within a group, in pixels.
        photons: detections per pixel wanted in a merged frame.
        typical: the paper's group size, used when motion and light allow it.
        min_groups: level 1 gets at least this many groups (if the capture allows 2).
        max_binning: largest level-1 binning.
        groups_per_period: level-1 groups per period of a vibration the probe found
            (m is at most its period over this): level 1's keyframes must sample the
            motion for its interpolation to follow it; at 1.7 groups per period the
            trajectory aliases (a 45 Hz, 4 px vibration at 100 000 frames in the dark,
            m = 1300: level 1 6.0 px, level 3 0.60 px; m = 740: 0.38 and 0.10 px), while
            the suite's 30 Hz captures run 4.4-7.3 groups per period.

    Returns:
        The :class:`GroupPlan` (``auto`` True).
    """
    speed, p = probe.speed_px_per_frame, probe.photons_per_pixel_per_frame
    cap = max(2, n_frames // min_groups)
    # a static scene (speed 0) allows any length; an unknown speed the paper's typical m
    m_motion = blur_px / max(speed, 1e-9) if speed is not None else float(typical)

    def plan(m: float, binning: int, reason: str) -> GroupPlan:
        if m > cap:
            m, reason = cap, reason + f"; capped at {cap} for {min_groups} groups"
        m = max(2, int(float(f"{m:.2g}")))
        return GroupPlan(m, binning, p * m if p is not None else None, speed,
                         speed * m if speed is not None else None, reason, True, probe)

    if p is None:  # intensity frames: no photon noise to average away, only motion to follow
        return plan(min(16.0, m_motion), 1, "intensity frames: a short group (at most 16 frames)")
    m = min(float(typical), m_motion)
    if speed is None:
        reason = f"the paper's typical {typical} frames (the motion pre-pass found no structure)"
    elif m_motion < typical:
        reason = f"motion: {speed:.4f} px/frame allows {m_motion:.0f} frames of {blur_px:g} px smear"
    else:
        reason = f"the paper's typical {typical} frames (motion {speed:.4f} px/frame allows more)"
    m_light = photons / max(p, 1e-12)
    if m_light > m:  # the dark: up to twice the smear budget, binning makes up the rest
        m = min(m_light, 2 * m_motion)
        reason = (f"light: {p:.2e} photons/pixel/frame needs {m_light:.0f} frames "
                  f"for {photons:g} photons/pixel")
    period = probe.vibration_period_frames
    if period is not None and m > period / groups_per_period:
        m = period / groups_per_period
        reason += (f"; a {probe.vibration_px:.2g} px vibration every {period:.0f} frames: "
                   f"{groups_per_period} groups per period")
    result = plan(m, 1, reason)
    binning = math.ceil(math.sqrt(photons / max(p * result.group_size, 1e-12)))
    return replace(result, binning=int(min(max_binning, max(1, binning))))


def plan_group_size(group_size: int | str, source) -> GroupPlan:
    """Resolve a spec's ``group_size`` for ``source``: an integer as given, ``"auto"`` measured.

    The capture is probed either way (the confidence report uses the photon rate and
    speed), except with ``source`` None, which only an integer allows.

    Raises:
        ValueError: for a value that is neither a positive integer nor ``"auto"``.
    """
    from ..flicker import detect_flicker

    if group_size == "auto":
        return whole_flicker_periods(choose_group_size(probe_capture(source), source.n_frames),
                                     detect_flicker(source), source.n_frames)
    if isinstance(group_size, int) and group_size >= 2:
        if source is None:
            return GroupPlan(group_size)
        probe = probe_capture(source)  # for the confidence report only
        p, speed = probe.photons_per_pixel_per_frame, probe.speed_px_per_frame
        return GroupPlan(group_size, 1, p * group_size if p is not None else None, speed,
                         speed * group_size if speed is not None else None, "set in the spec", False, probe,
                         detect_flicker(source))
    raise ValueError(f"group_size: expected an integer >= 2 or 'auto', got {group_size!r}")


def short_of_light(plan: GroupPlan, n_frames: int, *, tolerance: float = 0.8) -> str | None:
    """A note when an explicit group size gathers clearly fewer photons than the budget wants.

    The light limit of :func:`choose_group_size` (10 detections per pixel per merged
    frame) is where level 1's registrations stay reliable; an explicit m below
    ``tolerance`` times the group size ``auto`` would choose for that reason runs as set,
    with this note (measured: the README's low-light example, 20 000 frames at flux
    0.05, m = 500 instead of the budget's 690: 0.48 px instead of 0.24).

    Args:
        plan: the plan of an explicit ``group_size`` (with its probe).
        n_frames: binary frames in the capture.
        tolerance: fraction of the budget's group size below which the note is made.

    Returns:
        One line naming both group sizes and the budget's reason, or None (``auto``, no
        probe, or enough light).
    """
    if plan.auto or plan.probe is None or plan.photons_per_pixel_per_group is None:
        return None
    suggested = choose_group_size(plan.probe, n_frames)
    if not suggested.reason.startswith("light") or plan.group_size >= tolerance * suggested.group_size:
        return None
    return (f"group size {plan.group_size} (set in the spec) gathers {plan.photons_per_pixel_per_group:.3g} "
            f"photons per pixel per group; the photon budget (group_size: auto) would choose "
            f"{suggested.group_size} ({suggested.reason})")


def whole_flicker_periods(plan: GroupPlan, flicker: Any, n_frames: int, *, min_groups: int = 5,
                          max_extra_levels: int = 2) -> GroupPlan:
    """Lengthen ``plan``'s groups to whole periods of a lamp flickering over part of the scene.

    A lamp lighting part of the scene makes that part of every merged frame as bright as
    the lamp was, on average, during the group, and shows it where the scene was when
    the lamp was bright: both change from group to group unless every group spans whole
    flicker periods, and registrations are biased alike (measured on simulated half-lit
    captures: 0.4-5 px where steady light gives 0.1 px). With groups of k whole periods
    every virtual exposure sees the lamp's mean level (the paper's Sec. 6 suggests
    virtual exposures adapted to the flicker). Longer groups smear the first level
    more; the later levels warp each frame before merging, and one more level per
    doubling of m (at most ``max_extra_levels``) keeps the last level's keyframes as
    dense as planned.

    Args:
        plan: the group-size plan for steady light.
        flicker: the :class:`~photonpano.flicker.Flicker` found in the capture, or None.
        n_frames: binary frames in the capture.
        min_groups: level 1 keeps at least this many groups (else the plan is unchanged).
        max_extra_levels: most levels added.

    Returns:
        ``plan`` with ``flicker`` set and, for partial flicker, m = k whole periods
        (k = m / period rounded, at least 1) and ``extra_levels``.
    """
    plan = replace(plan, flicker=flicker)
    if flicker is None or not flicker.partial:
        return plan
    periods = max(1, round(plan.group_size / flicker.period_frames))
    m = int(round(periods * flicker.period_frames))
    if m == plan.group_size or m > n_frames // min_groups:
        return plan
    extra = int(min(max_extra_levels, max(0, round(math.log2(m / plan.group_size)))))
    p, speed = plan.photons_per_pixel_per_group, plan.speed_px_per_frame
    reason = (f"{plan.reason}; then {periods} whole period(s) of the {flicker.frequency_hz:.4g} Hz flicker over part "
              f"of the scene ({m} frames)")
    return replace(plan, group_size=m, reason=reason, extra_levels=extra,
                   photons_per_pixel_per_group=None if p is None else p * m / plan.group_size,
                   blur_px=None if speed is None else speed * m)
