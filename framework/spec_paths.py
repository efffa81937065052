"""Relative paths in spec files mean "next to the spec" (see :func:`resolve_relative_paths`)."""

from __future__ import annotations

import typing
from pathlib import Path
from typing import Any, Literal

from .host import PluginHost
from .spec_defaults import DEFAULT_PLUGINS
from .stages import STAGES

__all__ = ["resolve_relative_paths"]


def _is_path_field(annotation: Any) -> bool:
    """True if a field annotation is ``Path`` or contains it (``Path | None``, ``list[Path]``)."""
    if annotation is Path:
        return True
    return any(_is_path_field(arg) for arg in typing.get_args(annotation))


def _literals(annotation: Any) -> set[Any]:
    """Values of the ``Literal`` members of an annotation (``Literal["colorspad"] | Path`` -> {"colorspad"})."""
    if typing.get_origin(annotation) is Literal:
        return set(typing.get_args(annotation))
    return set().union(*(_literals(arg) for arg in typing.get_args(annotation)))


def resolve_relative_paths(data: dict[str, Any], host: PluginHost, base_dir: Path) -> dict[str, Any]:
    """Return a copy of ``data`` whose relative stage paths are joined to ``base_dir``.

    A spec file's relative paths (e.g. ``source: {path: capture.npy}``) mean "next to
    the spec", wherever the command runs; paths given with ``--set`` keep meaning
    "relative to the working directory" (they are resolved at validation). Only fields
    whose type is a path (``Path``, ``Path | None``, ``list[Path]``) of the selected
    plugin's config are touched; unknown plugins are left for validation to report.

    Args:
        data: a spec mapping as read from YAML.
        host: the plugin host (to find each stage's config class).
        base_dir: the folder of the spec file.

    Returns:
        A new mapping (``data`` is not modified).
    """
    out = dict(data)
    for stage in STAGES:
        section = out.get(stage)
        if not isinstance(section, dict):
            continue
        config = host.registry(stage).get(section.get("plugin", DEFAULT_PLUGINS.get(stage, "")))
        if config is None:
            continue
        section = dict(section)
        for name, field in config.model_fields.items():
            value = section.get(name)
            if not _is_path_field(field.annotation) or value is None or (
                    isinstance(value, str) and value in _literals(field.annotation)):
                continue
            if isinstance(value, str) and value and not Path(value).is_absolute():
                section[name] = str(base_dir.absolute() / value)
            elif isinstance(value, list):
                section[name] = [str(base_dir.absolute() / v) if isinstance(v, str) and not Path(v).is_absolute()
                                 else v for v in value]
        out[stage] = section
    return out
