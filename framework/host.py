"""Plugin discovery and the per-stage registries.

Every plugin, built-in or third-party, is a module named by an entry point in the
``photonpano.plugins`` group and registered with the same ``PluginManager.register``
call. A plugin that fails to import or registers bad objects is recorded as broken and
reported by ``photonpano plugins``; it does not stop the others.

Environment controls:
    PHOTONPANO_DISABLE_PLUGINS: comma-separated entry-point names to block.
    PHOTONPANO_DISABLE_PLUGIN_AUTOLOAD: if set, load no entry points (for tests).
    PHOTONPANO_TRACE_PLUGINS: if set, print every hook call to stderr.
    PHOTONPANO_PLUGIN_TIMEOUT_S: seconds instead of :data:`PLUGIN_IMPORT_TIMEOUT_S`
        (a positive number; anything else keeps the default).
    PHOTONPANO_HOOK_TIMEOUT_S: the limit of one stage call at run time (see
        :mod:`photonpano.watchdog`).

A third-party plugin module imports, and its registration hooks run, in a daemon thread
given :data:`PLUGIN_IMPORT_TIMEOUT_S`: one that hangs there (a network call, a lock, a
``sleep``) is reported as broken with a warning naming it, and the command goes on.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys
import threading
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import pluggy

from . import hookspecs
from .errors import PluginError
from .stages import STAGES, StageConfig

__all__ = ["GROUP", "PLUGIN_IMPORT_TIMEOUT_S", "PluginInfo", "PluginHost"]

GROUP = "photonpano.plugins"
"""The entry-point group that names plugin modules."""

PLUGIN_IMPORT_TIMEOUT_S = 10.0
"""Seconds a third-party plugin module may take to import (``EntryPoint.load``), and each
of its registration hooks to return, before it is reported as hung and left out (its
other hooks are then skipped); photonpano's own plugins run without a limit. Two hung
plugins still leave ``photonpano validate`` and ``plugins`` well under 30 s."""

_HUNG: dict[str, str] = {}
"""Plugin code that did not finish in this process (an entry point's target, or ``"hooks of
NAME"``) -> the note reported. Never called again: the thread still inside holds that
module's import lock (or the plugin's state)."""

_REGISTER_HOOKS = {
    "source": "photonpano_register_sources",
    "resampler": "photonpano_register_resamplers",
    "merger": "photonpano_register_mergers",
    "locator": "photonpano_register_locators",
    "interpolator": "photonpano_register_interpolators",
    "compositor": "photonpano_register_compositors",
    "pose_estimator": "photonpano_register_pose_estimators",
}


@dataclass(frozen=True)
class PluginInfo:
    """One row of ``photonpano plugins``.

    Attributes:
        key: the plugin key used in specs (e.g. ``"opencv-sift"``), or the entry-point
            name for a module that failed to load.
        stage: stage kind (``source``, ``locator``, ...), or ``"?"`` if unknown.
        module: the Python module that defines it.
        distribution: the installed distribution that provides it.
        version: that distribution's version.
        status: ``"ok"``, ``"unavailable: ..."`` (missing optional dependency, with the
            install command), ``"collision: ..."`` (an entry-point name or plugin key
            already taken, e.g. a third party's ``opencv-sift``: ignored, the built-in
            keeps it) or ``"broken: ..."``.
    """

    key: str
    stage: str
    module: str
    distribution: str
    version: str
    status: str


class PluginHost:
    """Typed facade over pluggy: discovery, blocking and per-stage registries.

    Args:
        autoload: load plugins from the ``photonpano.plugins`` entry points (the only
            route, built-ins included) unless ``PHOTONPANO_DISABLE_PLUGIN_AUTOLOAD`` is set.

    Attributes:
        pm: the pluggy plugin manager (use the methods below rather than ``pm.hook``).
        broken: entry-point or plugin name -> reason it is broken.
        collisions: entry-point names and plugin keys offered twice (the built-in, else
            the first registered, keeps them); also listed in ``broken``.
    """

    def __init__(self, autoload: bool = True) -> None:
        self.pm = pluggy.PluginManager("photonpano")
        self.pm.add_hookspecs(hookspecs)
        self.broken: dict[str, str] = {}
        self.collisions: list[str] = []
        self._dists: dict[str, tuple[str, str]] = {}
        self._ignored: dict[str, tuple[str, str]] = {}  # entry points not loaded (collisions, hangs): their dist
        self._registries: dict[str, dict[str, type[StageConfig]]] | None = None
        for name in filter(None, os.environ.get("PHOTONPANO_DISABLE_PLUGINS", "").split(",")):
            self.pm.set_blocked(name.strip())
        if autoload and not os.environ.get("PHOTONPANO_DISABLE_PLUGIN_AUTOLOAD"):
            self.load_entry_points()
        if os.environ.get("PHOTONPANO_TRACE_PLUGINS"):
            self.pm.trace.root.setwriter(sys.stderr.write)
            self.pm.enable_tracing()

    def load_entry_points(self) -> None:
        """Register every module named in the ``photonpano.plugins`` entry-point group.

        photonpano's own entry points load first and keep their names: a third-party
        entry point of the same name is not loaded and is reported (in ``broken`` and
        ``collisions``). A plugin that raises anything at import, ``SystemExit``
        included, is recorded as broken (``KeyboardInterrupt`` still interrupts), and so
        is a third-party module whose import takes longer than
        :data:`PLUGIN_IMPORT_TIMEOUT_S` (with a warning naming it).
        """
        eps = sorted(importlib.metadata.entry_points(group=GROUP), key=lambda ep: not _is_builtin_ep(ep))
        for ep in eps:
            dist = ep.dist.name if ep.dist else "?"
            version = ep.dist.version if ep.dist else "?"
            if self.pm.is_blocked(ep.name):
                continue
            if self.pm.has_plugin(ep.name):
                owner = self._dists.get(ep.name, ("?", ""))[0]
                note = (f"entry point {ep.name!r} of {dist} ({ep.value}) is ignored: the name is taken by "
                        f"{owner}")
                self.broken[f"{ep.name} ({dist})"] = note
                self._ignored[f"{ep.name} ({dist})"] = (dist, version)
                self.collisions.append(note)
                continue
            try:
                loaded = ep.load() if _is_builtin_ep(ep) else _in_time(
                    ep.load, ep.value, f"plugin {ep.name!r} of {dist} ({ep.value}): its import")
                self.register(loaded, name=ep.name)
            except _Hung as hung:
                self.broken[ep.name] = str(hung)
                self._ignored[ep.name] = (dist, version)
                continue
            except KeyboardInterrupt:
                raise
            except BaseException as exc:  # a broken plugin (even one calling sys.exit) is reported, not fatal
                self.broken[ep.name] = f"{dist}: cannot load {ep.value}: {type(exc).__name__}: {exc}"[:300]
                continue
            self._dists[ep.name] = (dist, version)

    def register(self, plugin: object, name: str) -> None:
        """Register a plugin object or module under ``name`` (also used by tests).

        Raises:
            PluginError: if a hook implementation matches no spec or has bad arguments.
        """
        try:
            self.pm.register(plugin, name=name)
            self.pm.check_pending()
        except pluggy.PluginValidationError as exc:
            if self.pm.is_registered(plugin):
                self.pm.unregister(plugin)
            raise PluginError(f"plugin {name!r}: {exc}") from None
        self._invalidate()

    def unregister(self, name: str) -> None:
        """Remove the plugin registered under ``name``."""
        self.pm.unregister(name=name)
        self._invalidate()

    @property
    def hook(self) -> Any:
        """The hook relay, for lifecycle calls (``host.hook.photonpano_run_start(...)``)."""
        return self.pm.hook

    def _build_registries(self) -> dict[str, dict[str, type[StageConfig]]]:
        registries: dict[str, dict[str, type[StageConfig]]] = {s: {} for s in STAGES}
        for stage, hook_name in _REGISTER_HOOKS.items():
            base = STAGES[stage]
            # Registration hooks take no arguments: call each implementation on its own
            # so that errors name the plugin that caused them. Built-ins first, then in
            # registration order: the first to offer a key keeps it.
            impls = getattr(self.pm.hook, hook_name).get_hookimpls()
            for impl in sorted(impls, key=lambda i: not _is_builtin(i.plugin)):
                try:
                    offered = list((impl.function() if _is_builtin(impl.plugin) else _in_time(
                        impl.function, f"hooks of {impl.plugin_name}",
                        f"plugin {impl.plugin_name!r}: {hook_name}")) or [])
                except _Hung as hung:
                    self.broken[impl.plugin_name] = str(hung)
                    continue
                except KeyboardInterrupt:
                    raise
                except BaseException as exc:
                    self.broken[impl.plugin_name] = f"{hook_name} raised {type(exc).__name__}: {exc}"[:300]
                    continue
                for cls in offered:
                    problem = _check_config_class(cls, base, stage)
                    key = cls.model_fields["plugin"].default if not problem else None
                    if not problem and key in registries[stage]:
                        other = registries[stage][key]
                        problem = (f"{stage} key {key!r} of {cls.__module__} is ignored: already registered "
                                   f"by {other.__module__}")
                        self.collisions.append(f"plugin {impl.plugin_name!r}: {problem}")
                    if problem:
                        self.broken[impl.plugin_name] = f"{hook_name}: {problem}"
                        continue
                    registries[stage][key] = cls
        return registries

    def _invalidate(self) -> None:
        self._registries = None
        self.collisions = [c for c in self.collisions if c.startswith("entry point")]

    def registry(self, stage: str) -> dict[str, type[StageConfig]]:
        """Return plugin key -> config class for one stage kind.

        Args:
            stage: one of ``source``, ``resampler``, ``merger``, ``locator``,
                ``interpolator``, ``compositor``.

        Raises:
            KeyError: for an unknown stage kind.
        """
        if self._registries is None:
            self._registries = self._build_registries()
        return self._registries[stage]

    def plugin_infos(self) -> list[PluginInfo]:
        """Return one :class:`PluginInfo` per registered key and per broken plugin."""
        rows: list[PluginInfo] = []
        modules = {getattr(p, "__name__", ""): n for n, p in self.pm.list_name_plugin()}
        for stage in STAGES:
            for key, cls in sorted(self.registry(stage).items()):
                ep_name = modules.get(cls.__module__, "")
                dist, version = self._dists.get(ep_name, ("(registered in code)", ""))
                missing = cls.missing_requirements()
                status = f"unavailable: needs {', '.join(missing)}: {cls.install_hint}" if missing else "ok"
                rows.append(PluginInfo(key, stage, cls.__module__, dist, version, status))
        for name, reason in sorted(self.broken.items()):
            kind = "collision" if _is_collision(reason) else "broken"
            dist = self._dists.get(name) or self._ignored.get(name) or ("?", "?")
            rows.append(PluginInfo(name, "?", "", *dist, f"{kind}: {reason}"))
        return rows

    def versions(self) -> dict[str, str]:
        """Return distribution name -> version of every loaded plugin distribution."""
        return {dist: version for dist, version in self._dists.values()}


class _Hung(Exception):
    """Plugin code (an import, a registration hook) did not finish within :data:`PLUGIN_IMPORT_TIMEOUT_S`."""


def _time_limit() -> float:
    """``PHOTONPANO_PLUGIN_TIMEOUT_S`` if a positive number, else :data:`PLUGIN_IMPORT_TIMEOUT_S`."""
    try:
        value = float(os.environ.get("PHOTONPANO_PLUGIN_TIMEOUT_S", ""))
    except ValueError:
        return PLUGIN_IMPORT_TIMEOUT_S
    return value if 0 < value < float("inf") else PLUGIN_IMPORT_TIMEOUT_S


def _in_time(call: Callable[[], Any], key: str, what: str) -> Any:
    """``call()`` in a daemon thread, waiting at most :data:`PLUGIN_IMPORT_TIMEOUT_S` seconds (see :func:`_time_limit`).

    Args:
        call: the plugin code to run (``ep.load``, a registration hook).
        key: what hung is remembered by (an entry point's target, a plugin name): it is
            not called again in this process.
        what: the code named in the warning, e.g. ``"plugin 'x' of dist (mod): its import"``.

    Returns:
        What ``call`` returned.

    Raises:
        _Hung: ``call`` did not finish in time (or ``key`` hung earlier in this
            process); a one-line warning naming ``what`` is issued once.
        BaseException: whatever ``call`` raised (``SystemExit`` and
            ``KeyboardInterrupt`` included), re-raised in the calling thread.
    """
    if key in _HUNG:
        raise _Hung(_HUNG[key])
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as exc:  # handed to the caller, which decides
            outcome["error"] = exc

    thread = threading.Thread(target=run, name="photonpano-plugin-code", daemon=True)
    thread.start()
    limit = _time_limit()
    thread.join(limit)
    if thread.is_alive():
        note = f"{what} did not finish within {limit:g} s (hangs?); left out"
        _HUNG[key] = note
        warnings.warn(note, stacklevel=3)
        raise _Hung(note)
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


def _is_collision(reason: str) -> bool:
    """Whether a reason in ``PluginHost.broken`` is a name or key collision (the messages made above)."""
    return reason.startswith("entry point ") or ": already registered by " in reason


def _is_builtin(plugin: object) -> bool:
    """Whether a registered plugin object is one of photonpano's built-in plugin modules."""
    return (getattr(plugin, "__name__", "") or "").startswith("photonpano.plugins.")


def _is_builtin_ep(ep: importlib.metadata.EntryPoint) -> bool:
    return ep.value.startswith("photonpano.plugins.") and (ep.dist is None or ep.dist.name == "photonpano")


def _check_config_class(cls: Any, base: type[StageConfig], stage: str) -> str | None:
    """Return why ``cls`` is not a valid config class of ``stage``, or None."""
    if not (isinstance(cls, type) and issubclass(cls, base)):
        return f"returned {cls!r}, expected a {base.__name__} subclass"
    default = cls.model_fields.get("plugin").default if "plugin" in cls.model_fields else None
    if not isinstance(default, str) or not default:
        return f"{cls.__name__}.plugin must default to its plugin key (a Literal string)"
    return None
