"""Default settings for a capture: which source reads it, and settings that fit its frames.

``photonpano pano INPUT`` (and ``compare``) start from :func:`spec_for_capture`: the
source plugin that reads ``INPUT`` and, for conventional (intensity) video such as a
Photron clip or an MP4 of a high-speed camera, settings that fit a few hundred frames
or fewer that are each already a good exposure, rather than 100 000 binary frames:

- ``merger: mean`` (average linear intensity, not the photon MLE);
- ``levels: 2`` and pairwise registration at every level (``level_schemes: [pairwise]``):
  footage from a static or slow camera is often dominated by moving objects, which
  registration against the panorama follows (a falling ball dragged a static camera's
  estimate by 52 px), while pairwise feature registration with the per-pair motion
  model choice (GRIC, ``motion: auto``) keeps to the static background;
- the group size m is ``auto`` as for every capture (:mod:`photonpano.budget`): from
  the frames' light and apparent speed, capped so that level 1 has at least 5 groups and
  at most 16 frames per group for intensity frames (3 for the 15-frame Photron clip).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .errors import PhotonpanoError

__all__ = ["spec_for_capture", "INTENSITY_SETTINGS"]

INTENSITY_SETTINGS: dict[str, Any] = {"merger": "mean", "levels": 2, "level_schemes": ["pairwise"]}
"""Settings ``pano`` gives captures of intensity frames (see the module docstring)."""


def spec_for_capture(path: Path, host: Any) -> dict[str, Any]:
    """Return the spec mapping ``photonpano pano`` uses for a capture file or folder.

    Args:
        path: a .npy photon cube, a folder of SwissSPAD .bin files, a video, an image
            folder or a Photron .mraw (any input a source plugin claims through
            ``photonpano_source_for_input``).
        host: the plugin host.

    Returns:
        ``{"source": {...}}`` plus, for intensity sources (config class attribute
        ``kind == "intensity"``), :data:`INTENSITY_SETTINGS`.

    Raises:
        PhotonpanoError: if ``path`` does not exist or no source plugin reads it.
    """
    if not path.exists():
        raise PhotonpanoError(f"input {path} does not exist")
    source = host.hook.photonpano_source_for_input(path=path)
    if source is None:
        raise PhotonpanoError(f"no source plugin reads {path} (supported: .npy photon cubes, folders of "
                              ".bin readouts, videos, image folders, .mraw; see `photonpano plugins`)")
    config_class = host.registry("source").get(source.get("plugin"))
    if getattr(config_class, "kind", "binary") != "intensity":
        return {"source": source}
    return {"source": source, **INTENSITY_SETTINGS}
