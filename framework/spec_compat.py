"""Keys of earlier specs, read under their present names (so old spec files keep working).

Each function moves one key of a spec mapping in place, before validation, and raises
``ValueError`` (reported as a spec error) where the old and the new key are both given.
"""

from __future__ import annotations

from typing import Any

__all__ = ["move_scale", "move_refine_locator"]


def move_scale(data: dict[str, Any], default_compositor: str) -> None:
    """``scale: 2`` -> ``compositor: {scale: 2}``: the super-resolution scale is the compositor's."""
    if "scale" not in data:
        return
    scale = data.pop("scale")
    section = data.get("compositor", default_compositor)
    section = {"plugin": section} if isinstance(section, str) else dict(section or {})
    if "scale" in section and section["scale"] != scale:
        raise ValueError(f"scale is given twice ({scale!r} and compositor.scale {section['scale']!r}); "
                         "write it once, as compositor.scale")
    section.setdefault("plugin", default_compositor)
    data["compositor"] = {**section, "scale": scale}


def move_refine_locator(data: dict[str, Any]) -> None:
    """``refine_locator: X`` -> ``mosaic: {locator: X}``, ``null`` -> ``level_schemes: [pairwise]``."""
    if "refine_locator" not in data:
        return
    refine = data.pop("refine_locator")
    if refine is None:
        if data.setdefault("level_schemes", ["pairwise"]) != ["pairwise"]:
            raise ValueError("refine_locator: null and level_schemes are both given; write level_schemes only")
        return
    mosaic = dict(data.get("mosaic") or {})
    if "locator" in mosaic:
        raise ValueError("refine_locator and mosaic.locator are both given; write mosaic.locator only")
    data["mosaic"] = {**mosaic, "locator": refine}
