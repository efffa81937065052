import importlib.metadata
import re
import sys
import types
from pathlib import Path
from typing import Literal

import pytest
from photonpano import hookimpl, hookspecs
from photonpano.errors import PluginError
from photonpano.host import GROUP, PluginHost
from photonpano.stages import LocatorConfig

BUILTINS = {"simulate", "npy-cube", "midpoint", "constant", "flux-mle", "opencv-sift", "cubic-lk"}


def test_builtins_come_through_the_entry_point_group(host):
    keys = {info.key for info in host.plugin_infos()}
    assert BUILTINS <= keys
    names = {ep.name for ep in importlib.metadata.entry_points(group=GROUP)}
    assert {"simulate", "opencv-sift"} <= names
    assert all(i.distribution == "photonpano" for i in host.plugin_infos() if i.key in BUILTINS)


def _fake_entry_points(monkeypatch, extra):
    real = importlib.metadata.entry_points

    def entry_points(group=None, **kw):
        eps = list(real(group=group, **kw))
        return eps + extra if group == GROUP else eps
    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)


def test_a_broken_third_party_plugin_is_reported_not_fatal(monkeypatch):
    broken = importlib.metadata.EntryPoint("broken", "no_such_module_xyz:plugin", GROUP)
    _fake_entry_points(monkeypatch, [broken])
    host = PluginHost()
    assert "broken" in host.broken and "No module named" in host.broken["broken"]
    assert "opencv-sift" in host.registry("locator")  # the others still load
    assert any(i.key == "broken" and i.status.startswith("broken") for i in host.plugin_infos())


def test_third_party_locator_registers_like_a_builtin(monkeypatch, host):
    module = types.ModuleType("photonpano_fake_locator")

    class FakeConfig(LocatorConfig):
        plugin: Literal["fake-locator"] = "fake-locator"

    @hookimpl
    def photonpano_register_locators():
        return [FakeConfig]

    module.photonpano_register_locators = photonpano_register_locators
    host.register(module, name="fake")
    assert host.registry("locator")["fake-locator"] is FakeConfig
    host.unregister("fake")
    assert "fake-locator" not in host.registry("locator")


def test_bad_registrations_mark_the_plugin_broken(bare_host):
    dup = types.SimpleNamespace(photonpano_register_locators=hookimpl(lambda: [int]))
    bare_host.register(dup, name="bad")
    assert bare_host.registry("locator") == {}
    assert "expected a LocatorConfig subclass" in bare_host.broken["bad"]


def test_misspelled_hook_is_a_plugin_error(bare_host):
    typo = types.SimpleNamespace(photonpano_register_locator=hookimpl(lambda: []))
    with pytest.raises(PluginError, match="plugin 'typo'"):
        bare_host.register(typo, name="typo")


def test_blocking_by_name(monkeypatch):
    monkeypatch.setenv("PHOTONPANO_DISABLE_PLUGINS", "opencv-sift")
    assert "opencv-sift" not in PluginHost().registry("locator")


def test_every_hook_is_documented():
    doc = (Path(__file__).parents[2] / "docs" / "hooks.md").read_text()
    hooks = [name for name in dir(hookspecs) if name.startswith("photonpano_")]
    assert hooks
    for name in hooks:
        assert re.search(rf"^## `{name}", doc, re.M), f"{name} missing from docs/hooks.md"


def test_registration_imports_no_heavy_backend():
    import subprocess

    code = ("import sys; from photonpano.host import PluginHost; h = PluginHost(); "
            "[h.registry(s) for s in ('source','resampler','merger','locator','interpolator')]; "
            "print(sorted(m for m in ('cv2','torch','kornia','pycolmap','numba') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
