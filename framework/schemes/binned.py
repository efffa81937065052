"""A scheme run on the capture binned k x k: :class:`Binned` (the photon budget's registration binning).

Motion is estimated on merged frames, and the locators register them at a fraction of
the sensor resolution anyway; merging them binned in the first place gives the locators
the same images for a k^2-th of the merging work (:mod:`photonpano.budget.grid`).
:class:`Binned` hands its scheme the binned capture and binned homographies and turns
its keyframes and registrations back into sensor pixels, so the level loop, the
schemes, mergers and locators need not know about binning (as OpenCV's stitcher keeps
its work scale inside matching and estimation).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from ..budget.grid import RegistrationGrid
from ..executor import Executor
from ..records import Groups, LocateResult
from .base import LevelScheme, LevelTask

__all__ = ["Binned"]


class Binned(LevelScheme):
    """``scheme`` on the capture binned by ``grid`` (see the module).

    Several wrappers may share one grid (the pairwise and the mosaic scheme of a run):
    the grid counts the binned photons once and is closed once.

    Args:
        scheme: the scheme to run on binned frames.
        grid: the :class:`~photonpano.budget.grid.RegistrationGrid` of the run (one per
            motion estimate: it holds the binned block store).
    """

    def __init__(self, scheme: LevelScheme, grid: RegistrationGrid) -> None:
        """Wrap ``scheme``; its name and needs are the wrapper's."""
        self.scheme, self.grid = scheme, grid
        self.name = scheme.name
        self.needs_template = scheme.needs_template

    def prepare(self, levels: Sequence[Groups], group_size: int, executor: Executor) -> None:
        """With two or more levels to run, count the binned photons once for all of them.

        (:meth:`~photonpano.budget.grid.RegistrationGrid.count_once`.)
        """
        if len(levels) >= 2:
            boundaries = np.concatenate([np.r_[g.start, g.stop] for g in levels])
            self.grid.count_once(boundaries, group_size, executor)

    def locate(self, task: LevelTask) -> LocateResult:
        """Run the scheme on the binned capture; its keyframes and registrations in sensor pixels."""
        binned = dataclasses.replace(task, source=self.grid.source, homographies=self.grid.inward(task.homographies))
        return self.grid.located_outward(self.scheme.locate(binned))

    def close(self) -> None:
        """Delete the grid's block store, if any."""
        self.grid.close()
