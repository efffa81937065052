"""photonpano: motion estimation and panoramas from single-photon cameras.

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

import pluggy

__version__ = "0.1.0"

hookimpl = pluggy.HookimplMarker("photonpano")
"""Marker for hook implementations of photonpano plugins."""

hookspec = pluggy.HookspecMarker("photonpano")
"""Marker for photonpano hook specifications (used in :mod:`photonpano.hookspecs`)."""

__all__ = ["__version__", "hookimpl", "hookspec"]
