"""Former home of the level loop and the panorama, kept so that existing imports work.

The loop is :mod:`photonpano.levels`; its schemes are :mod:`photonpano.schemes`; the pose
graph :mod:`photonpano.posegraph`; the guards :mod:`photonpano.guards`; the records
:mod:`photonpano.records`; the panorama :mod:`photonpano.compose`. New code imports
from those.
"""

from .compose import assemble_panorama, canvas_homographies, panorama_views
from .guards import plausible
from .levels import estimate_motion
from .posegraph import chain_keyframes, pairs_at_offsets, refine_keyframes
from .records import LevelResult, Panorama
from .schemes import locate_keyframes

__all__ = ["LevelResult", "chain_keyframes", "refine_keyframes", "pairs_at_offsets", "plausible",
           "locate_keyframes", "estimate_motion", "Panorama", "canvas_homographies", "assemble_panorama",
           "panorama_views"]
