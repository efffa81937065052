"""The plugins a spec gets for the stages it leaves out (re-exported by :mod:`photonpano.spec`).

A module of its own so that :mod:`photonpano.spec` and :mod:`photonpano.spec_paths` both
read it without importing each other.
"""

from __future__ import annotations

__all__ = ["DEFAULT_PLUGINS", "MOSAIC_PLUGINS"]

DEFAULT_PLUGINS: dict[str, str] = {
    "resampler": "midpoint",
    "merger": "flux-mle",
    "locator": "opencv-sift",
    "interpolator": "cubic-lk",
    "compositor": "drizzle",
    "pose_estimator": "pycolmap-sfm",
}
"""The paper's choice for each stage, used when a spec omits the stage."""

MOSAIC_PLUGINS: dict[str, str] = {"locator": "opencv-ecc", "template": "flux-canvas"}
"""Defaults of the ``mosaic`` scheme's locator and template compositor. A locator used
there starts from its config's ``template_defaults`` (settings for registering against a
low-noise panorama)."""
