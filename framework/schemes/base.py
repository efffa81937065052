"""The level scheme seam: how one level turns its groups into keyframe homographies.

A level re-samples the capture into groups, then hands them to its scheme, which merges
them (with the current estimate) and registers the merged frames: this is the paper's
*locate* step (Sec. 4). Two schemes are built in (:mod:`photonpano.schemes`):
``pairwise`` (the paper's: pairs of merged frames and a pose graph) and ``mosaic``
(each merged frame against the panorama of the current estimate). A scheme owns its
locators, its windows over the groups and the work it sends to the executor.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Callable, ClassVar, Sequence

import numpy as np
from numpy.typing import NDArray

from ..executor import Executor
from ..records import Groups, LocateResult
from ..stages import Merger, PhotonSource

__all__ = ["LevelTask", "LevelScheme"]


@dataclass(frozen=True)
class LevelTask:
    """One level's locate work, as the level loop hands it to a scheme.

    Attributes:
        level: 1-based level number.
        source: the capture.
        merger: the built merger.
        groups: the level's G groups (virtual exposures).
        homographies: (T, 3, 3) float64 current frame-to-panorama homographies (panorama
            coordinates: pixels of the middle binary frame).
        group_size: binary frames per group m (the trust threshold of template pixels).
        executor: where independent work runs.
        keep_merged: return the merged frames in the result (``outputs.merged_frames``).
        progress: called with the number of groups done, or None.
        crosscheck: also register consecutive merged frames directly against each
            other, held out of the keyframes (:attr:`LocateResult.crosscheck`), where
            the scheme's own registrations do not already relate them (the level
            loop asks for it at the last level; see :mod:`photonpano.uncertainty`), and
            chains of merged frames far apart (:attr:`LocateResult.chain`,
            :mod:`photonpano.long_pairs`) where the scheme supports them (mosaic).
    """

    level: int
    source: PhotonSource
    merger: Merger
    groups: Groups
    homographies: NDArray[np.float64]
    group_size: int
    executor: Executor
    keep_merged: bool = False
    progress: Callable[[int], None] | None = None
    crosscheck: bool = False

    @property
    def current(self) -> NDArray[np.float64]:
        """(G, 3, 3) float64 current homographies of the groups' reference frames."""
        return self.homographies[self.groups.reference]


class LevelScheme(abc.ABC):
    """Merges and registers one level's groups into keyframe homographies.

    Subclasses set :attr:`name` and implement :meth:`locate`. A scheme may be used for
    several levels of one run; it must not keep per-level state between calls.
    """

    name: ClassVar[str]
    needs_template: ClassVar[bool] = False
    """True if the scheme registers against the panorama of the current estimate: it cannot
    run at level 1."""

    def prepare(self, levels: Sequence[Groups], group_size: int, executor: Executor) -> None:
        """Called once before the levels run, with the groups of every level to run (default: nothing).

        Work done here for all levels (e.g. :class:`~photonpano.schemes.binned.Binned`
        counting the binned photons once) is timed with the first level's merge.

        Args:
            levels: the groups of each level to run, in order.
            group_size: binary frames per group m.
            executor: the run's executor.
        """

    def close(self) -> None:
        """Called once after the levels ran, or failed (default: nothing); must not raise twice."""

    @abc.abstractmethod
    def locate(self, task: LevelTask) -> LocateResult:
        """Merge the task's groups and register them.

        Args:
            task: the level's :class:`LevelTask`.

        Returns:
            The :class:`~photonpano.records.LocateResult`: G keyframe homographies in the
            coordinates of ``task.homographies``, and the registrations behind them.

        Raises:
            StageError: if nothing could be registered (naming the locator).
        """
