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
built at run time from the plugins installed, so third-party plugins validate exactly like built-ins.
"""

from __future__ import annotations

import difflib
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)

from .errors import PluginError, SpecError
from .faults import short_repr
from .host import PluginHost
from .stages import STAGES
from .yaml_guard import load_yaml

__all__ = ["DEFAULT_PLUGINS", "OutputsConfig", "spec_model", "load_spec", "validate_spec", "resolve_relative_paths",
           "apply_overrides", "dump_spec", "read_spec_file", "check_available"]

DEFAULT_PLUGINS: dict[str, str] = {
    "resampler": "midpoint",
    "merger": "flux-mle",
    "locator": "opencv-sift",
    "interpolator": "cubic-lk",
    "compositor": "drizzle",
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
    """Write each level's merged frames as ``level_<k>/merged.npy`` (float32 flux) and PNGs,
    at every level."""
    trajectory_plot: bool = True
    """Write ``trajectory.png``, the estimated (and true, if known) frame centres."""


class _SpecBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    @model_validator(mode="before")
    @classmethod
    def _scale_to_compositor(cls, data: Any) -> Any:
        # the super-resolution scale belongs to the compositor; keep top-level ``scale:`` working
        if not isinstance(data, dict) or "scale" not in data:
            return data
        data = dict(data)
        scale = data.pop("scale")
        section = data.get("compositor", DEFAULT_PLUGINS["compositor"])
        section = {"plugin": section} if isinstance(section, str) else dict(section or {})
        if "scale" in section and section["scale"] != scale:
            raise ValueError(f"scale is given twice ({scale!r} and compositor.scale {section['scale']!r}); "
                             "write it once, as compositor.scale")
        section.setdefault("plugin", DEFAULT_PLUGINS["compositor"])
        data["compositor"] = {**section, "scale": scale}
        return data

    @property
    def scale(self) -> float:
        """The compositor's super-resolution scale (canvas pixels per frame pixel)."""
        return self.compositor.scale

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


def _group_size(value: Any) -> Any:
    """Accept ``"auto"`` or an integer >= 2 as a group size, with one message for anything else."""
    if value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and value >= 2):
        return value
    raise ValueError("expected an integer >= 2 (binary frames per group) or auto")


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
        group_size=(Annotated[Union[Literal["auto"], Annotated[int, Field(ge=2)]],  # noqa: UP007
                              BeforeValidator(_group_size), Field(
            description="Binary frames per group m (virtual exposure length, in frames); auto: "
            "chosen from the capture's photon rate and apparent speed (photonpano.adaptive).")], "auto"),
        pair_offsets=(Annotated[list[Annotated[int, Field(ge=1)]], Field(
            min_length=1, description="Register merged frames g and g+k for each k; [1] is the "
            "paper's chain, more offsets are solved jointly against chaining drift.")], [1, 2, 4, 8, 16, 32, 64]),
        panorama_subbatch_px=(Annotated[float, Field(gt=0, le=2, description="Frames whose canvas "
                              "warps differ by less than this (canvas pixels) are warped together.")], 0.25),
        executor=(Literal["serial", "threads", "dask"], Field("threads", description="Where independent work "
                  "(groups, chunks) runs: the calling thread, a pool of threads, or a Dask cluster (a local one "
                  "of `workers` processes, or the scheduler at `dask_address`; see docs/scaling.md).")),
        workers=(Annotated[int, Field(ge=0, description="Threads of the executor, or worker processes of a local "
                                      "Dask cluster (0 = one per CPU core).")], 0),
        dask_address=(Annotated[str | None, Field(
            pattern=r"^(tcp|tls|inproc|ucx|ws|wss)://\S+$", description="executor dask: address of a running "
            "Dask scheduler, e.g. tcp://10.0.0.5:8786; null starts a local cluster of `workers` processes.")], None),
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
    data, node = read_spec_file(path)
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
            raise SpecError(f"--set {short_repr(item)}: expected stage.field=value")
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
    for slot in (*STAGES, "refine_locator"):
        stage = "locator" if slot == "refine_locator" else slot
        key = _plugin_of(data.get(slot))
        if not isinstance(key, str):
            continue
        registry = host.registry(stage)
        where = _blame_set(overridden, (slot,), data) or _where(node, (slot,), origin)
        if key not in registry:
            problems.append(f"{where}{slot}: {_unknown_plugin(stage, key, host)}")
        else:
            missing = registry[key].missing_requirements()
            if missing:
                problems.append(f"{where}{slot} ({key}): needs {', '.join(missing)}: "
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
            where = _blame_set(overridden, loc, data) or _where(node, loc, origin, data)
            lines.append(f"{where}{_describe_loc(loc, data)}: {str(err['msg'])[:200]}"
                         + (f" (got {short_repr(err['input'])})" if err["type"] not in ("missing",) and
                            not isinstance(err["input"], dict) else ""))
        raise SpecError(_listing(origin, lines)) from None


def check_available(spec: BaseModel) -> None:
    """Check that every plugin ``spec`` selects, ``refine_locator`` included, is usable.

    Raises:
        MissingDependency: naming the first plugin whose optional requirement is missing
            and the command that installs it.
    """
    for slot in (*STAGES, "refine_locator"):
        config = getattr(spec, slot, None)
        if config is not None:
            type(config).check_available()


def _listing(origin: str, problems: list[str], most: int = 20) -> str:
    """One line for one problem, else a header line and one indented line per problem (``most`` shown)."""
    if len(problems) == 1:
        return f"{origin}: {problems[0]}"
    more = [f"... and {len(problems) - most} more"] if len(problems) > most else []
    return (f"{origin}: invalid pipeline spec ({len(problems)} problems)\n  "
            + "\n  ".join(problems[:most] + more))


def _blame_set(overrides: list[str], loc: tuple, data: dict[str, Any]) -> str:
    """``"--set 'a.b=v': "`` for the last override that set the field at ``loc`` (or a parent), or ``""``."""
    parts = [str(p) for p in loc]
    if len(parts) > 1 and parts[0] in STAGES and _plugin_of(data.get(parts[0])) == parts[1]:
        del parts[1]  # the discriminator tag pydantic inserts
    dotted = ".".join(parts)
    for item in reversed(list(overrides)):
        key = item.partition("=")[0].strip()
        if key and (dotted == key or dotted.startswith(key + ".") or key.startswith(dotted + ".")):
            return f"--set {short_repr(item)}: "
    return ""


def _unknown_plugin(stage: str, key: str, host: PluginHost) -> str:
    names = sorted(host.registry(stage))
    close = difflib.get_close_matches(key, names, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    broken = [f"{n} is broken ({r})" for n, r in host.broken.items() if key in n]
    extra = f"; {broken[0]}" if broken else ""
    return f"unknown plugin {short_repr(key)}{hint} (installed {stage}s: {', '.join(names) or 'none'}){extra}"


def _describe_loc(loc: tuple, data: dict[str, Any]) -> str:
    """``('locator', 'opencv-sift', 'ratio')`` -> ``locator (opencv-sift).ratio``."""
    if not loc:
        return "spec"
    head, rest = str(loc[0]), list(loc[1:])
    if head in STAGES and rest and isinstance(rest[0], str) and _plugin_of(data.get(head)) == rest[0]:
        head = f"{head} ({rest.pop(0)})"
    text = ".".join([head, *map(str, rest)])
    return text if len(text) <= 120 else f"{text[:117]}..."


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
