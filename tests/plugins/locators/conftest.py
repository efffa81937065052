"""Fixtures of the locator tests: the real registration pair as merged frames."""

from __future__ import annotations

import numpy as np
import pytest
from locator_cases import DATA


@pytest.fixture(scope="session")
def real_pair():
    """The real image pair as merged frames: frame 0 = source.png, frame 1 = target.png.

    Pair (0, 1) wants H_TARGET_TO_SOURCE. The target's border (colour (128, 0, 0), where
    the warp left the source) is untrusted.
    """
    import cv2
    from photonpano.stages import MergedFrames

    source, target = cv2.imread(str(DATA / "source.png")), cv2.imread(str(DATA / "target.png"))
    gray = np.stack([cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (source, target)])
    masks = np.ones(gray.shape, bool)
    masks[1] = ~np.all(target == (0, 0, 128), axis=-1)
    flux = gray.astype(np.float32)
    return MergedFrames(flux=flux, frames=np.ones_like(flux), images=gray, masks=masks)
