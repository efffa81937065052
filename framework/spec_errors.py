"""Where a spec problem is: YAML line numbers, ``--set`` blame, plugin names in messages.

Helpers of :mod:`photonpano.spec`: a validation error's location (``("locator",
"opencv-sift", "ratio")``) becomes ``line 3: locator (opencv-sift).ratio``, or the
``--set`` override that set it.
"""

from __future__ import annotations

import difflib
import typing
from collections.abc import Sequence
from typing import Any

import yaml
from pydantic import BaseModel

from .faults import short_repr
from .host import PluginHost
from .stages import STAGES

__all__ = ["PLUGIN_SLOTS", "listing", "blame_set", "strip_tags", "unknown_plugin", "describe_loc", "plugin_of",
           "section_at", "where", "fields_at", "unknown_field_hint", "without_sections"]

PLUGIN_SLOTS: dict[tuple[str, ...], str] = {**{(stage,): stage for stage in STAGES},
                                            ("mosaic", "locator"): "locator", ("mosaic", "template"): "compositor",
                                            ("refine_locator",): "locator"}
"""Where a spec names a plugin (path of keys) -> the stage kind of that plugin
(``refine_locator``: the mosaic scheme's locator under its former name)."""


def listing(origin: str, problems: list[str], most: int = 20) -> str:
    """One line for one problem, else a header line and one indented line per problem (``most`` shown)."""
    if len(problems) == 1:
        return f"{origin}: {problems[0]}"
    more = [f"... and {len(problems) - most} more"] if len(problems) > most else []
    return (f"{origin}: invalid pipeline spec ({len(problems)} problems)\n  "
            + "\n  ".join(problems[:most] + more))


def blame_set(overrides: Sequence[str], loc: tuple, data: dict[str, Any]) -> str:
    """``"--set 'a.b=v': "`` for the last override that set the field at ``loc`` (or a parent), or ``""``."""
    dotted = ".".join(str(p) for p in strip_tags(loc))
    for item in reversed(list(overrides)):
        key = item.partition("=")[0].strip()
        if key and (dotted == key or dotted.startswith(key + ".") or key.startswith(dotted + ".")):
            return f"--set {short_repr(item)}: "
    return ""


def strip_tags(loc: tuple) -> tuple:
    """``loc`` without the discriminator tags pydantic inserts after each plugin slot."""
    out: list[Any] = []
    for i, part in enumerate(loc):
        if i and tuple(loc[:i]) in PLUGIN_SLOTS and isinstance(part, str):
            continue
        out.append(part)
    return tuple(out)


def unknown_plugin(stage: str, key: str, host: PluginHost) -> str:
    """``unknown plugin 'x'; did you mean 'y'? (installed ...)`` for a key not in ``stage``'s registry."""
    names = sorted(host.registry(stage))
    close = difflib.get_close_matches(key, names, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    broken = [f"{n} is broken ({r})" for n, r in host.broken.items() if key in n]
    extra = f"; {broken[0]}" if broken else ""
    return f"unknown plugin {short_repr(key)}{hint} (installed {stage}s: {', '.join(names) or 'none'}){extra}"


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The first pydantic model class inside a field annotation (``X``, ``Annotated[X, ...]``, ``X | None``)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def fields_at(model: type[BaseModel], loc: tuple, host: PluginHost) -> list[str] | None:
    """The field names of the (sub-)model at ``loc`` of a spec, or None where ``loc`` leads nowhere known.

    Args:
        model: the ``PipelineSpec`` model (:func:`photonpano.spec.spec_model`).
        loc: a pydantic error location of a *section*, with the plugin tags pydantic
            inserts after each plugin slot (``("locator", "opencv-sift")``); ``()`` is
            the spec itself.
        host: the plugin host whose registries resolve those tags.
    """
    cls: type[BaseModel] | None = model
    path: tuple = ()
    i = 0
    while i < len(loc):
        path += (loc[i],)
        if path in PLUGIN_SLOTS:
            if i + 1 >= len(loc):
                return None
            cls = host.registry(PLUGIN_SLOTS[path]).get(str(loc[i + 1]))
            i += 2
        else:
            field = cls.model_fields.get(str(loc[i])) if cls is not None else None
            cls = _model_in(field.annotation) if field is not None else None
            i += 1
        if cls is None:
            return None
    return list(cls.model_fields) if cls is not None else None


def unknown_field_hint(name: str, fields: list[str] | None, most: int = 12) -> str:
    """``"; did you mean 'locator'?"`` for a misspelt field, else the fields expected (or ``""``).

    Uses :func:`difflib.get_close_matches` as :func:`unknown_plugin` does; without a close
    match, lists the expected fields when there are at most ``most`` of them.
    """
    if not fields:
        return ""
    close = difflib.get_close_matches(str(name), [f for f in fields if f != "plugin"], n=1)
    if close:
        return f"; did you mean {close[0]!r}?"
    shown = [f for f in fields if f != "plugin"]
    return f" (expected one of: {', '.join(shown)})" if 0 < len(shown) <= most else ""


def without_sections(data: dict[str, Any], paths: list[tuple[str, ...]]) -> dict[str, Any]:
    """A copy of a spec mapping with the sections at ``paths`` removed (the rest shared, not copied)."""
    out = dict(data)
    for path in paths:
        parent = out
        for key in path[:-1]:
            child = parent.get(key)
            if not isinstance(child, dict):
                break
            parent[key] = child = dict(child)
            parent = child
        else:
            parent.pop(path[-1], None)
    return out


def describe_loc(loc: tuple, data: dict[str, Any]) -> str:
    """``('locator', 'opencv-sift', 'ratio')`` -> ``locator (opencv-sift).ratio``."""
    if not loc:
        return "spec"
    words: list[str] = []
    for i, part in enumerate(loc):
        if i and tuple(loc[:i]) in PLUGIN_SLOTS and isinstance(part, str):
            words[-1] += f" ({part})"
        else:
            words.append(str(part))
    text = ".".join(words)
    return text if len(text) <= 120 else f"{text[:117]}..."


def section_at(data: Any, path: tuple[str, ...]) -> Any:
    """The value at ``path`` in a spec mapping (None where missing)."""
    for key in path:
        data = data.get(key) if isinstance(data, dict) else None
    return data


def plugin_of(section: Any) -> str | None:
    """The plugin key a spec section names (a string, or a mapping's ``plugin``), or None."""
    if isinstance(section, str):
        return section
    return section.get("plugin") if isinstance(section, dict) else None


def where(node: Any, loc: tuple, origin: str, data: dict[str, Any] | None = None) -> str:
    """Return ``"line N: "`` for the YAML node at ``loc`` (union tags skipped), or ``""``."""
    line = None
    current = node
    for part in strip_tags(loc):
        if not isinstance(current, yaml.MappingNode):
            break
        found = next(((k, v) for k, v in current.value if k.value == str(part)), None)
        if found is None:
            break
        line, current = found[0].start_mark.line + 1, found[1]
    return f"line {line}: " if line is not None else ""
