"""The mosaic scheme's stage configs from a spec's ``mosaic`` section (for :class:`~photonpano.reconstruction.Stages`).

- :func:`robust_template`: the template compositor made robust, for while ``reject_movers`` is on.
- :func:`affine_locator` and :func:`affine_from_level`: the locator of the mosaic levels after
  the first ``mosaic.perspective_levels``, which register affine corrections.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..locator import LocatorConfig
    from ..spec_model import PipelineSpec

__all__ = ["affine_from_level", "affine_locator", "robust_template"]


def robust_template(mosaic: Any) -> Any:
    """The mosaic scheme's template compositor config made robust, for while ``reject_movers`` is on.

    A mover that enters the template (its faint ghost along its path) is not caught by
    the disagreement test and pulls the registrations; the robust merge
    (:mod:`photonpano.robust_merge`) keeps it out, and its left-out fraction is the
    scheme's mover detection. Compositors without a ``robust`` field are used as
    configured.
    """
    template = mosaic.template
    if "robust" in type(template).model_fields:
        template = template.model_copy(update={"robust": True})
    return template


def affine_locator(locator: LocatorConfig) -> LocatorConfig | None:
    """``locator`` with ``motion: affine``; None where its ``motion`` is not ``homography`` (or it has none).

    A mosaic level's registration against the panorama determines the perspective terms
    (``p7``, ``p8``) the least, and each level's bias in them adds up
    (``mosaic.perspective_levels``; docs/accuracy.md, "Affine corrections after the first
    mosaic level").
    """
    if getattr(locator, "motion", None) != "homography":
        return None
    return locator.model_copy(update={"motion": "affine"})


def affine_from_level(spec: PipelineSpec) -> int | None:
    """The first level (1-based) whose mosaic registrations are affine, or None where none is.

    The levels after the first ``spec.mosaic.perspective_levels`` mosaic levels
    (``level_schemes``), the flicker plan's extra levels included; None with
    ``perspective_levels: null`` or no mosaic level.
    """
    from ..spec import level_schemes

    names, kept = level_schemes(spec), spec.mosaic.perspective_levels
    if kept is None or "mosaic" not in names:
        return None
    return names.index("mosaic") + 1 + kept
