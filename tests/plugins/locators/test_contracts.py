"""photonpano.testing's contract suite, run on every built-in locator.

These are the checks a third-party locator runs on itself (see docs/writing_plugins.md);
running them here keeps the kit honest and the built-ins within the contract. Each
built-in is held to about 3x its measured mean corner error on the kit's pairs (the
largest of the shifted, perspective and half-turned pairs): opencv-orb, opencv-ecc,
kornia-sift and pycolmap-sift 0.046 px (bar 0.15 px), kornia-direct 0.15 px (bar
0.4 px); opencv-sift (no sub-pixel polish) 0.40 px keeps the kit's default 0.5 px.
"""

import pytest
from photonpano.plugins.locators.kornia_direct import KorniaDirectConfig
from photonpano.plugins.locators.kornia_sift import KorniaSiftConfig
from photonpano.plugins.locators.opencv_ecc import OpenCVEccConfig
from photonpano.plugins.locators.opencv_features import OpenCVOrbConfig
from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig
from photonpano.plugins.locators.pycolmap_sift import PycolmapSiftConfig
from photonpano.testing import LocatorContract


class _OneTorchThread:
    """Configs of the kornia locators; torch on one thread (the CI machine has two cores)."""

    def make_config(self, tmp_path_factory):
        if not self.config_class.missing_requirements():
            import torch

            torch.set_num_threads(1)
        return super().make_config(tmp_path_factory)


class TestOpenCVSift(LocatorContract):
    config_class = OpenCVSiftConfig
    entry_point = "opencv-sift"


class TestOpenCVOrb(LocatorContract):
    tolerance_px = 0.15
    config_class = OpenCVOrbConfig
    entry_point = "opencv-orb"


class TestOpenCVEcc(LocatorContract):
    tolerance_px = 0.15
    config_class = OpenCVEccConfig
    entry_point = "opencv-ecc"
    direct = True


@pytest.mark.slow
class TestKorniaSift(_OneTorchThread, LocatorContract):
    tolerance_px = 0.15
    config_class = KorniaSiftConfig
    config_kwargs = {"device": "cpu", "max_features": 1000}
    entry_point = "kornia-sift"


@pytest.mark.slow
class TestKorniaDirect(_OneTorchThread, LocatorContract):
    tolerance_px = 0.4
    config_class = KorniaDirectConfig
    config_kwargs = {"device": "cpu"}
    entry_point = "kornia-direct"
    direct = True


class TestPycolmapSift(LocatorContract):
    tolerance_px = 0.15
    config_class = PycolmapSiftConfig
    entry_point = "pycolmap-sift"
