"""Pipeline specs: YAML in, one validated pydantic model out, errors with line numbers.

A spec names one plugin per stage (a mapping with a ``plugin`` key and that plugin's
own fields, or just the key as a string), plus the number of levels, the group size m,
the super-resolution scale and the outputs::

    version: 1
    source: {plugin: npy-cube, path: capture.npy}
    locator: {plugin: opencv-sift, ratio: 0.75}
    levels: 3
    group_size: 500

Omitted stages use the paper's defaults (``midpoint``, ``flux-mle``, ``opencv-sift``,
``cubic-lk``). The stage slots are discriminated unions built at run time from the
plugins installed, so third-party plugins validate exactly like built-ins.
"""

from __future__ import annotations

import difflib
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator

from .errors import PluginError, SpecError
from .host import PluginHost
from .stages import STAGES

__all__ = ["DEFAULT_PLUGINS", "OutputsConfig", "spec_model", "load_spec", "validate_spec", "resolve_relative_paths",
           "apply_overrides", "dump_spec"]

DEFAULT_PLUGINS: dict[str, str] = {
    "resampler": "midpoint",
    "merger": "flux-mle",
    "locator": "opencv-sift",
    "interpolator": "cubic-lk",
    "pose_estimator": "pycolmap-sfm",
}
"""The paper's choice for each stage, used when a spec omits the stage."""

REFINE_DEFAULTS: dict[str, Any] = {"pyramid_levels": 2, "finest_level": 1, "iterations": 10, "blur": 5}
"""Settings of the default ``refine_locator`` (``opencv-ecc``): the residual motion at
levels >= 2 is about a pixel, so two pyramid levels and a few iterations suffice, and
against a low-noise template half resolution is enough (0.14 vs 0.13 px trajectory
RMSE at 100k frames, 2.5x less ECC time). A ``refine_locator`` mapping without
``plugin`` starts from these."""


class OutputsConfig(BaseModel):
    """Which optional outputs to write besides homographies, panorama and run.json."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    panorama_png: bool = True
    """Write ``panorama.png``, the tone-mapped 16-bit sRGB panorama."""
    merged_frames: bool = False
    """Write each level's merged frames as ``level_<k>/merged.npy`` (float32 flux) and PNGs
    (levels registered against the panorama stream their merged frames and have none to
    write; set ``refine_locator: null`` to dump every level)."""
    trajectory_plot: bool = True
    """Write ``trajectory.png``, the estimated (and true, if known) frame centres."""


class _SpecBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    @field_validator(*STAGES, "refine_locator", mode="before", check_fields=False)
    @classmethod
    def _plugin_shorthand(cls, value: Any) -> Any:
        return {"plugin": value} if isinstance(value, str) else value

    @field_validator("refine_locator", mode="before", check_fields=False)
    @classmethod
    def _refine_defaults(cls, value: Any) -> Any:
        # a mapping without a plugin adjusts the default refine locator
        if isinstance(value, dict) and "plugin" not in value:
            return {"plugin": "opencv-ecc", **REFINE_DEFAULTS, **value}
        return value


def _tagged(classes: list[type]) -> Any:
    return Annotated[Union[tuple(classes)], Field(discriminator="plugin")]  # noqa: UP007


def spec_model(host: PluginHost) -> type[BaseModel]:
    """Build the ``PipelineSpec`` model for the plugins installed in ``host``.

    Raises:
        PluginError: if a stage kind has no plugin at all.
    """
    slots: dict[str, Any] = {}
    for stage in STAGES:
        classes = list(host.registry(stage).values())
        if stage == "pose_estimator":  # optional: a spec with it runs `photonpano pose`
            tagged = _tagged(classes) if classes else None
            slots[stage] = (Annotated[Union[tagged, None], Field(  # noqa: UP007
                description="Experimental: estimate 6-DoF camera poses instead of a panorama.")], None)
            continue
        if not classes:
            raise PluginError(f"no {stage} plugins are installed (is photonpano installed?)")
        if stage == "source":
            slots[stage] = (_tagged(classes), ...)
        else:
            default_cls = host.registry(stage).get(DEFAULT_PLUGINS[stage], classes[0])
            slots[stage] = (_tagged(classes), Field(default_factory=default_cls))
    locators = host.registry("locator")
    ecc = locators.get("opencv-ecc")
    refine_default = (lambda: ecc(**REFINE_DEFAULTS)) if ecc is not None else (lambda: None)
    slots["refine_locator"] = (Annotated[Union[_tagged(list(locators.values())), None],  # noqa: UP007
                                          Field(description=(
                                              "Locator of levels >= 2, which register each merged frame "
                                              "against the panorama of the current estimate (frame-to-mosaic, "
                                              "no drift, one registration per group); null: every level "
                                              "registers pairs of merged frames with `locator` (the paper's "
                                              "scheme, slower)."))],
                               Field(default_factory=refine_default))
    model = create_model(
        "PipelineSpec",
        __base__=_SpecBase,
        version=(Literal[1], 1),
        **slots,
        levels=(Annotated[int, Field(ge=1, le=8, description="Number of levels (iterations of "
                                     "re-sample, merge, locate, interpolate).")], 3),
        group_size=(Annotated[int, Field(ge=2, description="Binary frames per group m (virtual "
                                         "exposure length, in frames).")], 500),
        pair_offsets=(Annotated[list[Annotated[int, Field(ge=1)]], Field(
            min_length=1, description="Register merged frames g and g+k for each k; [1] is the "
            "paper's chain, more offsets are solved jointly against chaining drift.")], [1, 2, 4, 8, 16, 32, 64]),
        scale=(Annotated[float, Field(gt=0, le=8, description="Super-resolution scale of the "
                                      "panorama canvas (canvas pixels per frame pixel).")], 1.0),
        panorama_subbatch_px=(Annotated[float, Field(gt=0, le=2, description="Frames whose canvas "
                              "warps differ by less than this (canvas pixels) are warped together.")], 0.25),
        executor=(Literal["serial", "threads"], Field("threads", description="Where independent work "
                  "(groups, chunks) runs: the calling thread, or a pool of threads.")),
        workers=(Annotated[int, Field(ge=0, description="Threads of the executor (0 = one per CPU core).")], 0),
        outputs=(OutputsConfig, Field(default_factory=OutputsConfig)),
    )
    model.__doc__ = "A photonpano pipeline: one plugin per stage and the method's settings."
    return model


def load_spec(path: Path, host: PluginHost, overrides: list[str] = ()) -> BaseModel:
    """Read, override and validate a YAML spec file.

    Args:
        path: the YAML file.
        host: the plugin host whose plugins the spec may use.
        overrides: ``"stage.field=value"`` strings (values parsed as YAML).

    Raises:
        SpecError: missing or unreadable file, bad YAML, unknown plugin or invalid
            field; the message lists every problem with its line.
    """
    try:
        text = path.read_text()
    except OSError as exc:
        raise SpecError(f"{path}: cannot read spec: {exc.strerror or exc}") from None
    try:
        node = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark else ""
        raise SpecError(f"{path}:{where} not valid YAML: {getattr(exc, 'problem', exc)}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise SpecError(f"{path}: a spec must be a mapping of stage and setting names, got {type(data).__name__}")
    data = resolve_relative_paths(data, host, path.parent)
    data = apply_overrides(data, overrides)
    return validate_spec(data, host, origin=str(path), node=node, overridden=overrides)


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
        config = host.registry(stage).get(section.get("plugin", DEFAULT_PLUGINS.get(stage)))
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


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Return a copy of ``data`` with ``"a.b=value"`` overrides applied (value as YAML).

    ``stage=key`` selects a plugin and ``stage.field=value`` sets one field.

    Raises:
        SpecError: for an override that is not ``path=value``.
    """
    import copy

    out = copy.deepcopy(data)
    for item in overrides:
        dotted, sep, raw = item.partition("=")
        if not sep or not dotted.strip():
            raise SpecError(f"--set {item!r}: expected stage.field=value")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError:
            value = raw
        keys = dotted.strip().split(".")
        target = out
        for key in keys[:-1]:
            child = target.get(key)
            if isinstance(child, str):  # plugin shorthand: "locator: opencv-sift"
                child = {"plugin": child}
            if not isinstance(child, dict):
                child = {"plugin": DEFAULT_PLUGINS[key]} if key in DEFAULT_PLUGINS else {}
            target[key] = child
            target = child
        target[keys[-1]] = value
    return out


def validate_spec(data: dict[str, Any], host: PluginHost, *, origin: str = "spec", node: Any = None,
                  overridden: list[str] = ()) -> BaseModel:
    """Validate a spec mapping against the installed plugins.

    Checks, in order: unknown or unavailable plugins (with "did you mean" and install
    hints), then every field. Selected plugins' optional dependencies are checked here,
    before any data is read.

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
    for stage in STAGES:
        section = data.get(stage)
        key = section if isinstance(section, str) else section.get("plugin") if isinstance(section, dict) else None
        if not isinstance(key, str):
            continue
        registry = host.registry(stage)
        where = _where(node, (stage,), origin)
        if key not in registry:
            problems.append(f"{where}{stage}: {_unknown_plugin(stage, key, host)}")
        else:
            missing = registry[key].missing_requirements()
            if missing:
                problems.append(f"{where}{stage} ({key}): needs {', '.join(missing)}: "
                                f"{registry[key].install_hint}")
    if problems:
        raise SpecError(_listing(origin, problems))
    model = spec_model(host)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = tuple(err["loc"])
            lines.append(f"{_where(node, loc, origin, data)}{_describe_loc(loc, data)}: {err['msg']}"
                         + (f" (got {err['input']!r})" if err["type"] not in ("missing",) and
                            not isinstance(err["input"], dict) else ""))
        raise SpecError(_listing(origin, lines)) from None


def _listing(origin: str, problems: list[str]) -> str:
    """One line for one problem, else a header line and one indented line per problem."""
    if len(problems) == 1:
        return f"{origin}: {problems[0]}"
    return f"{origin}: invalid pipeline spec ({len(problems)} problems)\n  " + "\n  ".join(problems)


def _unknown_plugin(stage: str, key: str, host: PluginHost) -> str:
    names = sorted(host.registry(stage))
    close = difflib.get_close_matches(key, names, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    broken = [f"{n} is broken ({r})" for n, r in host.broken.items() if key in n]
    extra = f"; {broken[0]}" if broken else ""
    return f"unknown plugin {key!r}{hint} (installed {stage}s: {', '.join(names) or 'none'}){extra}"


def _describe_loc(loc: tuple, data: dict[str, Any]) -> str:
    """``('locator', 'opencv-sift', 'ratio')`` -> ``locator (opencv-sift).ratio``."""
    if not loc:
        return "spec"
    head, rest = str(loc[0]), list(loc[1:])
    if head in STAGES and rest and isinstance(rest[0], str) and _plugin_of(data.get(head)) == rest[0]:
        head = f"{head} ({rest.pop(0)})"
    return ".".join([head, *map(str, rest)])


def _plugin_of(section: Any) -> str | None:
    if isinstance(section, str):
        return section
    return section.get("plugin") if isinstance(section, dict) else None


def _where(node: Any, loc: tuple, origin: str, data: dict[str, Any] | None = None) -> str:
    """Return ``"line N: "`` for the YAML node at ``loc`` (skipping union tags), or ``""``."""
    if node is None:
        return ""
    line = None
    current = node
    for i, part in enumerate(loc):
        if not isinstance(current, yaml.MappingNode):
            break
        match = next((v for k, v in current.value if k.value == str(part)), None)
        if match is None:
            key_node = next((k for k, _ in current.value if k.value == "plugin"), None)
            if i > 0 and key_node is not None and str(part) == _plugin_value(current):
                continue  # the discriminator tag pydantic inserts into the location
            break
        key = next(k for k, v in current.value if v is match)
        line = key.start_mark.line + 1
        current = match
    if line is None and loc:
        return ""
    return f"line {line}: " if line is not None else ""


def _plugin_value(node: Any) -> str | None:
    for k, v in node.value:
        if k.value == "plugin":
            return v.value
    return None


def dump_spec(spec: BaseModel) -> str:
    """Return the fully resolved spec (defaults filled in) as YAML text."""
    data = spec.model_dump(mode="json")
    return yaml.safe_dump(data, sort_keys=False)
