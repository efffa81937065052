"""What produced a run: photonpano's and the libraries' versions, the spec, the capture.

Every ``run.json`` (``photonpano run``, ``pano``, ``pose``) starts with
:func:`run_header`, so that a result can be traced to the code and settings behind it.
"""

from __future__ import annotations

import platform
from typing import TYPE_CHECKING, Any

from . import __version__
from .host import PluginHost

if TYPE_CHECKING:
    from .spec_model import PipelineSpec

__all__ = ["CORE_LIBRARIES", "run_header", "library_versions"]


#: distributions whose versions every run.json records (import name -> distribution).
CORE_LIBRARIES = {"numpy": "numpy", "cv2": "opencv-python-headless", "numba": "numba", "scipy": "scipy",
                  "pluggy": "pluggy", "pydantic": "pydantic"}


def run_header(spec: PipelineSpec, host: PluginHost, source: Any) -> dict[str, Any]:
    """Return the first keys of every ``run.json``: versions, the resolved spec, the capture.

    Returns:
        ``{"photonpano", "python", "versions", "plugins", "spec", "source"}`` (see
        :func:`library_versions` and ``PhotonSource.describe``).
    """
    return {"photonpano": __version__, "python": platform.python_version(), "versions": library_versions(spec),
            "plugins": host.versions(), "spec": spec.model_dump(mode="json"), "source": source.describe()}


def library_versions(spec: PipelineSpec | None = None) -> dict[str, str]:
    """Return the versions of the core libraries and of the optional backends ``spec`` uses.

    Args:
        spec: a validated ``PipelineSpec``; the ``requires`` of its stages' configs (e.g.
            torch and kornia for ``kornia-sift``) are added. None: core libraries only.

    Returns:
        ``{import name: version}``; ``"not installed"`` for a missing one. OpenCV's is
        ``cv2.__version__`` (whatever wheel provides it).
    """
    import importlib
    from importlib import metadata

    from .spec import plugin_configs

    names = list(CORE_LIBRARIES)
    if spec is not None:
        for config in plugin_configs(spec).values():
            names += [name for name in getattr(type(config), "requires", ()) if name not in names]
    versions: dict[str, str] = {}
    for name in names:
        try:
            versions[name] = str(getattr(importlib.import_module(name), "__version__"))
        except (ImportError, AttributeError):
            try:
                versions[name] = metadata.version(CORE_LIBRARIES.get(name, name))
            except metadata.PackageNotFoundError:
                versions[name] = "not installed"
    return versions
