"""Contract tests for photonpano plugins: subclass one class per plugin in your test suite.

Every plugin kind has a contract class whose ``test_*`` methods pytest collects when you
subclass it in a test module (name the subclass ``Test...``). Set the class attributes
and, for stages that need data, override the documented methods::

    # tests/test_contract.py of a third-party locator package
    from photonpano.testing import LocatorContract
    from photonpano_phasecorr.plugin import PhaseCorrConfig

    class TestPhaseCorr(LocatorContract):
        config_class = PhaseCorrConfig
        entry_point = "phasecorr"        # checks discovery through the entry point
        motion = "translation"           # the synthetic warps it must recover

The checks: the config class is a valid, documented, frozen, strict, picklable and
schema-exportable model of its stage; the plugin is found through its entry point and
selectable in a spec; registering it imports no heavy module; and the built object keeps
the stage's contract on tiny synthetic data (shapes, dtypes, coordinate conventions and
directions, failures flagged rather than raised, repeatable results). See
``docs/writing_plugins.md``.

This module imports pytest, numpy and pydantic only; OpenCV is imported by the tests
that make synthetic frames. Contract classes:

- :class:`PluginContract`: config-level checks shared by every kind;
- :class:`SourceContract`, :class:`ResamplerContract`, :class:`MergerContract`,
  :class:`LocatorContract`, :class:`InterpolatorContract`, :class:`CompositorContract`,
  :class:`PoseEstimatorContract`:
  the stage's behaviour.

Helpers for your own tests: :func:`textured_image`, :func:`synthetic_pair`,
:func:`merged_frames`, :func:`corner_error_px`, :func:`tiny_capture`.
"""

from ._captures import corner_error_px, merged_frames, synthetic_pair, textured_image, tiny_capture
from ._compositor import CompositorContract
from ._locator import LocatorContract
from ._plugin import HEAVY_MODULES, PluginContract
from ._pose import PoseEstimatorContract
from ._stages import InterpolatorContract, MergerContract, ResamplerContract, SourceContract

__all__ = [
    "PluginContract",
    "SourceContract",
    "ResamplerContract",
    "MergerContract",
    "LocatorContract",
    "InterpolatorContract",
    "CompositorContract",
    "PoseEstimatorContract",
    "textured_image",
    "synthetic_pair",
    "merged_frames",
    "corner_error_px",
    "tiny_capture",
    "HEAVY_MODULES",
]
