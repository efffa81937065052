"""The config-level contract every plugin passes (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

import json
import pickle
import re
import subprocess
import sys
from typing import Any, ClassVar

import pytest

from ..stages import STAGES, StageConfig

HEAVY_MODULES = ("cv2", "torch", "kornia", "pycolmap", "numba")
"""Modules that registering a plugin (importing its entry-point module) must not import."""


class PluginContract:
    """Checks every plugin config class must pass, whatever its stage kind.

    Class attributes (set them in your subclass):
        config_class: the plugin's config class (required).
        config_kwargs: field values for a valid instance (default: none; sources
            usually need some). Override :meth:`make_config` for values computed at test
            time (a temporary file, say).
        entry_point: the entry-point name in the ``photonpano.plugins`` group, to check
            discovery; None skips those checks (plugins registered in code).
        heavy_modules: modules that importing the plugin's entry-point module must not
            import (default :data:`HEAVY_MODULES`).
    """

    config_class: ClassVar[type[StageConfig]]
    config_kwargs: ClassVar[dict[str, Any]] = {}
    entry_point: ClassVar[str | None] = None
    heavy_modules: ClassVar[tuple[str, ...]] = HEAVY_MODULES

    # hooks -----------------------------------------------------------------------------

    def make_config(self, tmp_path_factory: pytest.TempPathFactory) -> StageConfig:
        """Return a valid config instance (default: ``config_class(**config_kwargs)``)."""
        return self.config_class(**self.config_kwargs)

    @pytest.fixture(scope="class")
    @classmethod
    def config(cls, tmp_path_factory: pytest.TempPathFactory) -> StageConfig:
        """A valid config instance of the plugin (one per test class)."""
        return cls().make_config(tmp_path_factory)

    @pytest.fixture(scope="class")
    @classmethod
    def built(cls, config: StageConfig) -> Any:
        """The built stage object (skipped with the install hint if an extra is missing)."""
        missing = type(config).missing_requirements()
        if missing:
            pytest.skip(f"needs {', '.join(missing)}: {type(config).install_hint}")
        return config.build()

    @property
    def key(self) -> str:
        """The plugin key (``plugin`` field default)."""
        return self.config_class.model_fields["plugin"].default

    # checks ------------------------------------------------------------------------------

    def test_config_class_is_a_stage_config(self) -> None:
        """Subclasses one stage's config base and pins a kebab-case ``plugin`` key."""
        assert issubclass(self.config_class, StageConfig)
        assert self.config_class.stage in STAGES, f"unknown stage kind {self.config_class.stage!r}"
        assert issubclass(self.config_class, STAGES[self.config_class.stage])
        assert isinstance(self.key, str) and re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", self.key), \
            f"plugin key {self.key!r} should be kebab-case"

    def test_every_field_is_documented(self) -> None:
        """Each field has a description (a docstring on the line below it)."""
        undocumented = [n for n, f in self.config_class.model_fields.items()
                        if n != "plugin" and not f.description]
        assert not undocumented, f"fields without a docstring: {undocumented}"
        assert (self.config_class.__doc__ or "").strip(), "the config class needs a docstring"

    def test_config_is_strict_frozen_and_round_trips(self, config: StageConfig) -> None:
        """Unknown fields are errors, instances are immutable, dumps validate back."""
        from pydantic import ValidationError

        with pytest.raises(ValidationError):
            self.config_class(**config.model_dump(), no_such_field_xyz=1)
        name = next((n for n in self.config_class.model_fields if n != "plugin"), "plugin")
        with pytest.raises((ValidationError, TypeError, AttributeError)):
            setattr(config, name, getattr(config, name))
        again = self.config_class.model_validate(json.loads(config.model_dump_json()))
        assert again == config

    def test_config_pickles(self, config: StageConfig) -> None:
        """Configs cross process boundaries (executors, multiprocessing) by pickle."""
        assert pickle.loads(pickle.dumps(config)) == config

    def test_schema_exports(self) -> None:
        """The JSON schema forbids extra keys and pins the plugin key."""
        schema = self.config_class.model_json_schema()
        assert schema.get("additionalProperties") is False
        assert self.key in json.dumps(schema["properties"]["plugin"])

    def test_optional_dependencies_have_an_install_hint(self) -> None:
        """A plugin with optional requirements says how to install them."""
        if self.config_class.requires:
            assert self.config_class.install_hint, "requires is set but install_hint is empty"

    def test_found_through_its_entry_point(self) -> None:
        """The entry point loads, registers the key, and ``photonpano plugins`` lists it."""
        if self.entry_point is None:
            pytest.skip("entry_point not set")
        import importlib.metadata

        from photonpano.host import GROUP, PluginHost

        names = {ep.name for ep in importlib.metadata.entry_points(group=GROUP)}
        assert self.entry_point in names, \
            f"no entry point {self.entry_point!r} in group {GROUP!r} (installed?)"
        host = PluginHost()
        assert self.entry_point not in host.broken, host.broken.get(self.entry_point)
        assert host.registry(self.config_class.stage).get(self.key) is not None
        info = next(i for i in host.plugin_infos() if i.key == self.key)
        assert info.stage == self.config_class.stage
        assert info.status == "ok" or info.status.startswith("unavailable"), info.status
        assert info.distribution not in ("?", "(registered in code)")

    def test_selectable_in_a_spec(self, config: StageConfig) -> None:
        """A spec naming the plugin validates into this config class.

        Skipped, naming the missing modules and the install hint, when the plugin's
        optional extra is not installed: a spec naming it is then rightly an error.
        """
        missing = self.config_class.missing_requirements()
        if missing:
            pytest.skip(f"needs {', '.join(missing)}: {self.config_class.install_hint}")
        if self.entry_point is None:
            pytest.skip("entry_point not set")
        from photonpano.host import PluginHost
        from photonpano.spec import validate_spec

        stage = self.config_class.stage
        data: dict[str, Any] = {"source": {"plugin": "simulate", "frames": 1000}}
        data[stage] = config.model_dump(mode="json")
        spec = validate_spec(data, PluginHost(), origin="contract")
        assert type(getattr(spec, stage)) is self.config_class or \
            type(getattr(spec, stage)).__name__ == self.config_class.__name__

    def test_registration_imports_no_heavy_module(self) -> None:
        """Importing the entry-point module (registration) leaves heavy modules unimported."""
        module = self.config_class.__module__
        code = (f"import sys, importlib; importlib.import_module({module!r}); "
                f"print(sorted(m for m in {self.heavy_modules!r} if m in sys.modules))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        assert out.strip() == "[]", f"{module} imports {out.strip()} at registration; import them in build()"
