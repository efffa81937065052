"""Resamplers ``midpoint`` (the paper's stratified re-sampling) and ``constant`` (ablation).

Paper Sec. 4, "Re-sample": level 1 splits the n binary frames into n/m (rounded) groups
of m frames spread over the whole capture, each referenced to its centre frame; every later
level adds groups centred between the previous ones, so the trajectory is sampled ever
more densely. ``constant`` keeps the level-1 groups at every level (paper Fig. 5).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from photonpano import hookimpl
from photonpano.stages import Groups, Resampler, ResamplerConfig
from pydantic import Field


def level_one_references(n_frames: int, group_size: int) -> np.ndarray:
    """Return the (G1,) int64 centre frames of the level-1 groups.

    G1 = n / m rounded groups of m frames spread evenly from the first
    frame to the last: ``m // 2 + k * (n - m) / (G1 - 1)``, rounded; exactly m apart
    where m divides n, a few frames more or less apart otherwise. (floor(n / m) groups end
    to end, as before, left up to m - 1 frames after the last group, all at the end of the
    capture, where level 1 extrapolated and every later level only anchored the end frame;
    measured: a 120 Hz lamp over half the scene, m = 838 whole periods, 726 frames left
    over: the outdoor camera 0.17 px, 1.3 px at its end, now 0.04 px over three seeds.)

    Raises:
        ValueError: if the capture holds fewer than ``2 * group_size`` frames (fewer
            than 4, the shortest capture anything can be registered in, say so).
    """
    end_to_end = n_frames // group_size
    if n_frames < 4:
        raise ValueError(f"a capture of {n_frames} frame{'s' if n_frames != 1 else ''} is too short to register: "
                         "at least 4 are needed (2 groups of at least 2 frames)")
    if end_to_end < 2:
        raise ValueError(f"a capture of {n_frames} frames gives {end_to_end} group(s) of "
                         f"{group_size} frames; at least 2 are needed (lower group_size to at most "
                         f"{n_frames // 2})")
    count = int(n_frames / group_size + 0.5)  # >= 2: end_to_end is
    first = group_size // 2
    return np.rint(np.linspace(first, n_frames - group_size + first, count)).astype(np.int64)


def groups_around(references: np.ndarray, n_frames: int, group_size: int) -> Groups:
    """Return groups of ``group_size`` frames centred on each reference, kept in the capture.

    A group that would leave the capture is shifted inside it; its reference frame is
    then off-centre (paper suppl. S.2: localising off-centre time slices).
    """
    refs = np.unique(np.asarray(references, dtype=np.int64))
    group_size = min(group_size, n_frames)
    start = np.clip(refs - group_size // 2, 0, n_frames - group_size)
    return Groups(start=start, stop=start + group_size, reference=refs)


class MidpointConfig(ResamplerConfig):
    """Stratified re-sampling: each level adds groups centred between the previous ones."""

    plugin: Literal["midpoint"] = "midpoint"
    growth: Annotated[float, Field(ge=0.25, le=4)] = 1.0
    """Group length at level k is m * growth**(k-1) frames, centred on the same reference
    frames. Later levels merge motion-compensated frames, so longer groups gather more
    photons without adding blur and sharpen registration; 1 is the paper's constant m."""
    anchor_ends: bool = True
    """From level 2 on, also reference the first and the last binary frame (groups of
    m/2 frames at the ends of the capture), so the ends of the trajectory are estimated
    rather than extrapolated (paper suppl. S.2, edge effects)."""

    def build(self) -> MidpointResampler:
        """Return the resampler."""
        return MidpointResampler(self)


class MidpointResampler(Resampler):
    """Level k has (G1 - 1) * 2**(k-1) + 1 groups, spaced about m / 2**(k-1) frames apart."""

    def __init__(self, config: MidpointConfig) -> None:
        self.config = config

    def groups(self, n_frames: int, group_size: int, level: int) -> Groups:
        """Return the groups of ``level`` (see :meth:`Resampler.groups`).

        Raises:
            ValueError: if the capture is too short for level 1 (see
                :func:`level_one_references`), or for ``level``: its groups would be
                centred less than one frame apart (``group_size / 2**(level-1) < 1``),
                so it could add no reference frame between the previous level's.
        """
        base = level_one_references(n_frames, group_size)
        steps = 2 ** (level - 1)
        if group_size < steps:
            most = group_size.bit_length()  # levels whose groups are at least one frame apart
            raise ValueError(f"groups of {group_size} frames allow at most {most} level{'s' if most != 1 else ''}: "
                             f"level {level}'s would be centred {group_size / steps:g} frames apart")
        fine = np.linspace(base[0], base[-1], (len(base) - 1) * steps + 1)
        refs = np.rint(fine).astype(np.int64)
        length = int(round(group_size * self.config.growth ** (level - 1)))
        groups = groups_around(refs, n_frames, length)
        if not (self.config.anchor_ends and level >= 2):
            return groups
        # A merged frame shows the scene displaced by the *mean* error of its frames, so
        # the end groups are half as long: their mean error stays closer to the error
        # of the end frame they are referenced to. A reference frame already at an end
        # (groups of 1 or 2 frames) is not anchored twice.
        half = max(group_size // 2, 1)
        head = slice(0, int(groups.reference[0] > 0))
        tail = slice(0, int(groups.reference[-1] < n_frames - 1))

        def with_ends(values: np.ndarray, first: int, last: int) -> np.ndarray:
            return np.concatenate([np.array([first], np.int64)[head], values, np.array([last], np.int64)[tail]])

        return Groups(start=with_ends(groups.start, 0, n_frames - half), stop=with_ends(groups.stop, half, n_frames),
                      reference=with_ends(groups.reference, 0, n_frames - 1))


class ConstantConfig(ResamplerConfig):
    """The same level-1 groups at every level (the paper's ablation, Fig. 5)."""

    plugin: Literal["constant"] = "constant"

    def build(self) -> ConstantResampler:
        """Return the resampler."""
        return ConstantResampler()


class ConstantResampler(Resampler):
    """The level-1 groups (n/m of m frames, rounded) at every level."""

    def groups(self, n_frames: int, group_size: int, level: int) -> Groups:
        """Return the level-1 groups whatever ``level`` is."""
        return groups_around(level_one_references(n_frames, group_size), n_frames, group_size)


@hookimpl
def photonpano_register_resamplers() -> list[type[ResamplerConfig]]:
    """Register ``midpoint`` and ``constant``."""
    return [MidpointConfig, ConstantConfig]
