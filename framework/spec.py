"""Pipeline specs: YAML in, one validated pydantic model out, errors with line numbers.

A spec names one plugin per stage (a mapping with a ``plugin`` key and that plugin's
own fields, or just the key as a string), plus the number of levels, the group size m
and the outputs; the super-resolution scale is the compositor's (``compositor: {plugin:
drizzle, scale: 2}``; a top-level ``scale: 2`` is moved there)::

    version: 1
    source: {plugin: npy-cube, path: capture.npy}
    locator: {plugin: opencv-sift, ratio: 0.75}
    levels: 3
    group_size: auto

Omitted stages use the paper's defaults (``midpoint``, ``flux-mle``, ``opencv-sift``,
``cubic-lk``) and the ``drizzle`` compositor. The stage slots are discriminated unions
built at run time from the plugins installed, so third-party plugins validate exactly like built-ins
(:mod:`photonpano.spec_model`); this module reads, overrides, validates and dumps specs.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import (
    BaseModel,
    ValidationError,
)

from .errors import SpecError
from .faults import short_repr
from .host import PluginHost
from .spec_defaults import DEFAULT_PLUGINS
from .spec_errors import (
    PLUGIN_SLOTS,
    blame_set,
    describe_loc,
    fields_at,
    listing,
    plugin_of,
    section_at,
    strip_tags,
    unknown_field_hint,
    unknown_plugin,
    where,
    without_sections,
)
from .spec_model import OutputsConfig, PipelineSpec, level_schemes, plugin_configs, spec_model
from .spec_paths import resolve_relative_paths
from .yaml_guard import control_character, load_yaml

__all__ = ["DEFAULT_PLUGINS", "OutputsConfig", "spec_model", "load_spec", "validate_spec", "resolve_relative_paths",
           "apply_overrides", "dump_spec", "read_spec_file", "capture_instead_of_spec", "check_available",
           "level_schemes", "plugin_configs"]


def load_spec(path: Path, host: PluginHost, overrides: Sequence[str] = ()) -> PipelineSpec:
    """Read, override and validate a YAML spec file.

    Args:
        path: the YAML file.
        host: the plugin host whose plugins the spec may use.
        overrides: ``"stage.field=value"`` strings (values parsed as YAML).

    Raises:
        SpecError: missing or unreadable file, a capture instead of a spec (naming
            ``photonpano pano``), bad YAML, unknown plugin or invalid field; the message
            lists every problem with its line.
    """
    capture = capture_instead_of_spec(path, host)
    if capture is not None:
        raise SpecError(capture)
    data, node = read_spec_file(path)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise SpecError(f"{path}: a spec must be a mapping of stage and setting names, got {type(data).__name__}")
    data = resolve_relative_paths(data, host, path.parent)
    data = apply_overrides(data, overrides)
    return validate_spec(data, host, origin=str(path), node=node, overridden=overrides)


SPEC_SUFFIXES = (".yaml", ".yml", ".json")
"""Suffixes always read as spec files, even where a source plugin would claim the path."""


def capture_instead_of_spec(path: Path, host: PluginHost) -> str | None:
    """The one-line message for a capture given where a spec is expected, or None.

    ``path`` is a capture when it exists, its suffix is not one of :data:`SPEC_SUFFIXES`
    and a source plugin claims it through ``photonpano_source_for_input`` (as for
    ``photonpano pano``): ``.npy`` cubes, ``.zarr`` folders, SwissSPAD ``.bin`` files or
    folders, Photron ``.mraw``, videos and image folders. A plugin failing in that hook
    counts as not claiming the path.
    """
    if not path.exists() or path.suffix.lower() in SPEC_SUFFIXES:
        return None
    try:
        source = host.hook.photonpano_source_for_input(path=path)
    except Exception:  # a plugin's bug here must not hide the spec's own error
        return None
    if not isinstance(source, dict):
        return None
    return (f"{path}: a capture (source {source.get('plugin')}), not a YAML pipeline spec; reconstruct it "
            f"with `photonpano pano {path}`")


def read_spec_file(path: Path) -> tuple[Any, Any]:
    """Read a YAML spec file safely (see :func:`photonpano.yaml_guard.load_yaml`).

    Returns:
        ``(data, node)``: the parsed value and its composed node (line numbers).

    Raises:
        SpecError: unreadable file, invalid UTF-8, invalid or oversized YAML, duplicate keys.
    """
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SpecError(f"{path}: cannot read spec: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise SpecError(f"{path}: line {line}: not valid UTF-8 text (byte 0x{raw[exc.start]:02x} at "
                        f"offset {exc.start})") from None
    return load_yaml(text, str(path))


def apply_overrides(data: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Return a copy of ``data`` with ``"a.b=value"`` overrides applied (value as YAML).

    ``stage=key`` selects a plugin and ``stage.field=value`` sets one field.

    Raises:
        SpecError: for an override that is not ``path=value``, or whose path holds a
            control character.
    """
    import copy

    out = copy.deepcopy(data)
    for item in overrides:
        dotted, sep, raw = item.partition("=")
        if not sep or not dotted.strip():
            raise SpecError(f"--set {short_repr(item)}: expected stage.field=value")
        if control_character(dotted) is not None:
            raise SpecError(f"--set {short_repr(item)}: the field path holds a control character")
        try:
            value = load_yaml(raw, f"--set {short_repr(item)}")[0] if raw.strip() else ""
        except SpecError as exc:
            if "not valid YAML" not in str(exc):
                raise
            value = raw
        keys = dotted.strip().split(".")
        target = out
        for key in keys[:-1]:
            child = target.get(key)
            if isinstance(child, str):  # plugin shorthand: "locator: opencv-sift"
                child = {"plugin": child}
            if not isinstance(child, dict):
                child = {"plugin": DEFAULT_PLUGINS[key]} if target is out and key in DEFAULT_PLUGINS else {}
            target[key] = child
            target = child
        target[keys[-1]] = value
    return out


def validate_spec(data: dict[str, Any], host: PluginHost, *, origin: str = "spec", node: Any = None,
                  overridden: Sequence[str] = ()) -> PipelineSpec:
    """Validate a spec mapping against the installed plugins.

    Checks unknown or unavailable plugins (with "did you mean" and install hints) and
    every field (unknown field names with "did you mean"), and reports all problems at
    once: a section naming an unknown plugin is left out of the field checks, so it does
    not hide the other sections' errors. Selected plugins' optional dependencies are
    checked here, before any data is read.

    Args:
        data: the spec as a mapping.
        host: the plugin host.
        origin: file name (or other origin) used in messages.
        node: the ``yaml.compose`` node of the file, for line numbers.
        overridden: the ``--set`` overrides applied, reported for fields they touched.

    Returns:
        A validated ``PipelineSpec`` instance.

    Raises:
        SpecError: listing every problem.
    """
    problems: list[str] = []
    unknown: list[tuple[str, ...]] = []
    for path, stage in PLUGIN_SLOTS.items():
        key = plugin_of(section_at(data, path))
        if not isinstance(key, str):
            continue
        registry = host.registry(stage)
        slot = ".".join(path)
        place = blame_set(overridden, path, data) or where(node, path, origin)
        if key not in registry:
            problems.append(f"{place}{slot}: {unknown_plugin(stage, key, host)}")
            unknown.append(path)
        else:
            missing = registry[key].missing_requirements()
            if missing:
                problems.append(f"{place}{slot} ({key}): needs {', '.join(missing)}: "
                                f"{registry[key].install_hint}")
    model = spec_model(host)
    try:
        # sections naming an unknown plugin are left out, so that the rest is still checked
        spec = model.model_validate(without_sections(data, unknown) if unknown else data)
    except ValidationError as exc:
        for err in exc.errors():
            loc = tuple(err["loc"])
            if any(strip_tags(loc)[:len(path)] == path for path in unknown):
                continue
            place = blame_set(overridden, loc, data) or where(node, loc, origin, data)
            msg = str(err["msg"])[:200]
            if err["type"] == "extra_forbidden" and loc:
                msg += unknown_field_hint(str(loc[-1]), fields_at(model, loc[:-1], host))
            problems.append(f"{place}{describe_loc(loc, data)}: {msg}"
                            + (f" (got {short_repr(err['input'])})" if err["type"] not in ("missing",) and
                               not isinstance(err["input"], dict) else ""))
    if problems:
        raise SpecError(listing(origin, sorted(problems, key=_line_of)))
    return spec


def _line_of(problem: str) -> float:
    """The YAML line a problem names (``line N: ...``), infinity for the rest (stable sort: ``--set`` last)."""
    match = re.match(r"line (\d+): ", problem)
    return int(match.group(1)) if match else float("inf")


def check_available(spec: PipelineSpec) -> None:
    """Check that every plugin ``spec`` uses (:func:`plugin_configs`) is usable.

    Raises:
        MissingDependency: naming the first plugin whose optional requirement is missing
            and the command that installs it.
    """
    for config in plugin_configs(spec).values():
        type(config).check_available()


def dump_spec(spec: BaseModel) -> str:
    """Return the fully resolved spec (defaults filled in) as YAML text."""
    data = spec.model_dump(mode="json")
    return yaml.safe_dump(data, sort_keys=False)
