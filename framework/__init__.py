"""photonpano: motion estimation and panoramas from single-photon cameras.

Run a pipeline from Python with :func:`photonpano.run` (a spec file, YAML text or a
mapping; returns homographies, panorama and summary) and read a finished run back with
:func:`photonpano.load`; see :mod:`photonpano.api`.

The method is "Panoramas from Photons" (Jungerman, Ingle, Gupta, ICCV 2023): stratified
temporal re-sampling of a photon cube, iterated over levels (re-sample, merge, locate,
interpolate), then every binary frame is warped onto one panorama canvas.

Writing a plugin takes five lines::

    from typing import Literal
    from photonpano import hookimpl
    from photonpano.stages import LocatorConfig

    class MyLocatorConfig(LocatorConfig):
        plugin: Literal["my-locator"] = "my-locator"
        def build(self): ...

    @hookimpl
    def photonpano_register_locators():
        return [MyLocatorConfig]

and an entry point in the ``photonpano.plugins`` group naming that module. See
``docs/writing_plugins.md``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:  # type checkers see the API's signatures; at run time it is imported on first use
    from .api import load, run

__version__ = "0.1.0"

hookimpl = pluggy.HookimplMarker("photonpano")
"""Marker for hook implementations of photonpano plugins."""

hookspec = pluggy.HookspecMarker("photonpano")
"""Marker for photonpano hook specifications (used in :mod:`photonpano.hookspecs`)."""

__all__ = ["__version__", "hookimpl", "hookspec", "run", "load"]


def __getattr__(name: str) -> Any:
    """Import the Python API on first use, so ``import photonpano`` stays cheap."""
    if name in ("run", "load"):
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'photonpano' has no attribute {name!r}")
