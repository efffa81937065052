"""Default settings for a capture: which source reads it, and settings that fit its frames.

``photonpano pano INPUT`` (and ``compare``) start from :func:`spec_for_capture`: the
source plugin that reads ``INPUT`` and, for conventional (intensity) video such as a
Photron clip or an MP4 of a high-speed camera, settings that fit a few hundred frames
or fewer that are each already a good exposure, rather than 100 000 binary frames:

- ``merger: mean`` (average linear intensity, not the photon MLE);
- ``levels: 2`` and pairwise registration at every level (``refine_locator: null``):
  footage from a static or slow camera is often dominated by moving objects, which
  registration against the panorama follows (a falling ball dragged a static camera's
  estimate by 52 px), while pairwise feature registration with the per-pair motion
  model choice (GRIC, ``motion: auto``) keeps to the static background;
- a group size m from the frame count and the frames' noise (:func:`video_group_size`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .errors import PhotonpanoError

__all__ = ["spec_for_capture", "video_group_size", "INTENSITY_SETTINGS"]

INTENSITY_SETTINGS: dict[str, Any] = {"merger": "mean", "levels": 2, "refine_locator": None}
"""Settings ``pano`` gives captures of intensity frames (see the module docstring)."""

#: signal-to-noise ratio wanted in a merged frame of intensity video
TARGET_SNR = 30.0


def spec_for_capture(path: Path, host: Any) -> dict[str, Any]:
    """Return the spec mapping ``photonpano pano`` uses for a capture file or folder.

    Args:
        path: a .npy photon cube, a folder of SwissSPAD .bin files, a video, an image
            folder or a Photron .mraw (any input a source plugin claims through
            ``photonpano_source_for_input``).
        host: the plugin host.

    Returns:
        ``{"source": {...}}`` plus, for intensity sources (config class attribute
        ``kind == "intensity"``), :data:`INTENSITY_SETTINGS` and a ``group_size`` from
        :func:`video_group_size` (the source is opened once to measure it).

    Raises:
        PhotonpanoError: if ``path`` does not exist, no source plugin reads it, or the
            source cannot be opened.
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
    opened = config_class.model_validate(source).build()
    return {"source": source, **INTENSITY_SETTINGS, "group_size": video_group_size(opened)}


def video_group_size(source: Any, *, target_snr: float = TARGET_SNR, min_groups: int = 5) -> int:
    """Choose the group size m for a capture of intensity frames.

    A merged frame of m frames has the noise of one frame divided by sqrt(m), so the
    noise asks for ``m >= (target_snr / snr)^2``; the motion estimate needs at least
    ``min_groups`` groups at level 1 (so the cubic interpolation has keyframes to
    follow), which caps m at ``n_frames // min_groups``. The single-frame SNR is
    measured on the first two frames: signal = median intensity, noise = the median
    absolute difference of the two frames / (0.6745 sqrt 2) (a robust sigma; motion
    between the frames only raises it, so m errs on the large side).

    Args:
        source: an opened intensity source (``sum_ranges`` gives linear intensity).
        target_snr: SNR wanted per merged frame (dimensionless).
        min_groups: fewest groups wanted at level 1.

    Returns:
        m >= 2 (binary frames per group).

    Raises:
        PhotonpanoError: if the capture has fewer than 4 frames (too short to estimate
            motion from).
    """
    n = int(source.n_frames)
    if n < 4:
        raise PhotonpanoError(f"{source.name}: {n} frames is too short to estimate motion (need at least 4)")
    cap = max(2, n // min_groups)
    pair = np.asarray(source.sum_ranges(np.array([0, 1, 2])), np.float64)
    signal = float(np.median(pair))
    sigma = float(np.median(np.abs(pair[0] - pair[1]))) / (0.6745 * math.sqrt(2))
    if signal <= 0:
        return cap
    wanted = math.ceil((target_snr * sigma / signal) ** 2) if sigma > 0 else 2
    return int(min(cap, max(2, wanted)))
