"""Where a spec problem is: YAML line numbers, ``--set`` blame, plugin names in messages.

Helpers of :mod:`photonpano.spec`: a validation error's location (``("locator",
"opencv-sift", "ratio")``) becomes ``line 3: locator (opencv-sift).ratio``, or the
``--set`` override that set it.
"""

from __future__ import annotations

import difflib
from typing import Any

import yaml

from .faults import short_repr
from .host import PluginHost
from .stages import STAGES

__all__ = ["PLUGIN_SLOTS", "listing", "blame_set", "strip_tags", "unknown_plugin", "describe_loc", "plugin_of",
           "section_at", "where"]

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


def blame_set(overrides: list[str], loc: tuple, data: dict[str, Any]) -> str:
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
