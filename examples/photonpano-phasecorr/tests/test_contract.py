"""photonpano's contract tests, run on this plugin (what every plugin package should do)."""

import numpy as np
from photonpano.testing import LocatorContract, corner_error_px, synthetic_pair
from photonpano_phasecorr.plugin import PhaseCorrConfig


class TestPhaseCorrContract(LocatorContract):
    config_class = PhaseCorrConfig
    entry_point = "phasecorr"
    motion = "translation"
    tolerance_px = 0.35


def test_recovers_integer_and_subpixel_shifts():
    for tx, ty in [(5.0, -3.0), (-7.25, 2.5), (0.4, 0.3)]:
        truth = np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1.0]])
        merged = synthetic_pair(truth, 160, 240, noise=0.01)
        result = PhaseCorrConfig().build().register_pairs(merged, np.array([[0, 1]]), np.eye(3)[None])
        assert result.ok[0]
        assert corner_error_px(result.homographies[0], truth, 240, 160) < 0.35
