"""Level schemes: how a level registers its merged frames (see :mod:`photonpano.schemes.base`).

- ``pairwise`` (:class:`PairwiseScheme`): the paper's scheme, pairs of merged frames
  chained and solved as a pose graph; the only scheme that can start from nothing, so
  level 1 always uses it.
- ``mosaic`` (:class:`MosaicScheme`): each merged frame against the panorama of the
  current estimate; no drift, one registration per group.

The spec selects one per level (``level_schemes``). Policies of the photon budget
(:class:`~photonpano.budget.Budget`) wrap or plug into them: :class:`Binned` runs a
scheme on the binned capture, :class:`PairCheck` checks the pairwise scheme's
registrations on binned frames.
"""

from .base import LevelScheme, LevelTask
from .binned import Binned
from .check import PairCheck
from .mosaic import MosaicScheme
from .pairwise import PairwiseScheme, locate_keyframes

__all__ = ["LevelScheme", "LevelTask", "PairwiseScheme", "MosaicScheme", "locate_keyframes", "Binned", "PairCheck"]
