"""photonpano.testing's contract suite, run on every built-in locator.

These are the checks a third-party locator runs on itself (see docs/writing_plugins.md);
running them here keeps the kit honest and the built-ins within the contract.
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
    config_class = OpenCVOrbConfig
    entry_point = "opencv-orb"


class TestOpenCVEcc(LocatorContract):
    config_class = OpenCVEccConfig
    entry_point = "opencv-ecc"
    direct = True


@pytest.mark.slow
class TestKorniaSift(_OneTorchThread, LocatorContract):
    config_class = KorniaSiftConfig
    config_kwargs = {"device": "cpu", "max_features": 1000}
    entry_point = "kornia-sift"


@pytest.mark.slow
class TestKorniaDirect(_OneTorchThread, LocatorContract):
    config_class = KorniaDirectConfig
    config_kwargs = {"device": "cpu"}
    entry_point = "kornia-direct"
    direct = True


class TestPycolmapSift(LocatorContract):
    config_class = PycolmapSiftConfig
    entry_point = "pycolmap-sift"
