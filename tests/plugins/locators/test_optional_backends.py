"""Optional backends: unavailable with an install command, refused early, imported lazily.

Listed as unavailable with the install command when missing, refused at validation
before any data is read, and never imported just to register or validate.
"""

import importlib.util
import subprocess
import sys

import pytest
from photonpano.errors import MissingDependency, SpecError
from photonpano.spec import validate_spec
from typer.testing import CliRunner

HINTS = {"kornia-sift": "pip install 'photonpano[kornia]'", "kornia-direct": "pip install 'photonpano[kornia]'",
         "pycolmap-sift": "pip install 'photonpano[colmap]'"}


@pytest.fixture
def without_backends(monkeypatch):
    """Pretend torch, kornia and pycolmap are not installed."""
    real = importlib.util.find_spec

    def find_spec(name, *args, **kwargs):
        return None if name.split(".")[0] in ("torch", "kornia", "pycolmap") else real(name, *args, **kwargs)
    monkeypatch.setattr(importlib.util, "find_spec", find_spec)


@pytest.mark.parametrize("key", sorted(HINTS))
def test_missing_extra_is_listed_with_its_install_command(host, without_backends, key):
    info = next(i for i in host.plugin_infos() if i.key == key)
    assert info.status.startswith("unavailable: needs ") and info.status.endswith(HINTS[key])


@pytest.mark.parametrize("key", sorted(HINTS))
def test_spec_selecting_a_missing_backend_fails_at_validation(host, without_backends, key):
    with pytest.raises(SpecError) as err:
        validate_spec({"source": {"plugin": "npy-cube", "path": "never-read.npy"}, "locator": key}, host)
    assert f"locator ({key}): needs" in str(err.value) and HINTS[key] in str(err.value)
    with pytest.raises(MissingDependency, match=r"photonpano\[(kornia|colmap)\]"):
        host.registry("locator")[key]().build()


def test_validate_command_prints_the_hint(tmp_path, without_backends):
    from photonpano.cli import app

    spec = tmp_path / "spec.yaml"
    spec.write_text("source: {plugin: npy-cube, path: x.npy}\nlocator: {plugin: kornia-direct, lr: 0.01}\n")
    result = CliRunner().invoke(app, ["validate", str(spec)])
    assert result.exit_code == 1
    assert "line 2: locator (kornia-direct): needs torch, kornia: pip install 'photonpano[kornia]'" in result.output


def test_validating_a_kornia_spec_imports_no_torch(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: {plugin: npy-cube, path: x.npy}\nlocator: {plugin: kornia-sift, device: cpu}\n")
    code = ("import sys; from typer.testing import CliRunner; from photonpano.cli import app; "
            f"r = CliRunner().invoke(app, ['validate', {str(spec)!r}]); "
            "print(r.exit_code, sorted(m for m in ('torch', 'kornia', 'pycolmap') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("[]"), out


@pytest.mark.parametrize("section, where", [
    ("mosaic: {locator: {plugin: kornia-direct}}", "line 2: mosaic.locator (kornia-direct)"),
    ("mosaic:\n  locator: kornia-direct", "line 3: mosaic.locator (kornia-direct)"),
    ("refine_locator: {plugin: kornia-direct}", "line 2: refine_locator (kornia-direct)"),  # its former name
])
def test_mosaic_locator_with_a_missing_extra_fails_at_validation(tmp_path, without_backends, section, where):
    """Issue 12: a refine_locator whose extra is missing passed `validate` and failed at level 2."""
    from photonpano.cli import app

    spec = tmp_path / "spec.yaml"
    spec.write_text(f"source: {{plugin: npy-cube, path: x.npy}}\n{section}\n")
    result = CliRunner().invoke(app, ["validate", str(spec)])
    assert result.exit_code == 1
    assert f"{where}: needs torch, kornia: pip install 'photonpano[kornia]'" in result.output


def test_plugin_configs_name_the_mosaic_slots_only_when_a_level_uses_them():
    from photonpano.host import PluginHost
    from photonpano.spec import plugin_configs, validate_spec

    host = PluginHost()
    pairwise = validate_spec({"source": {"plugin": "simulate"}, "level_schemes": ["pairwise"]}, host)
    assert set(plugin_configs(pairwise)) == {"source", "resampler", "merger", "locator", "interpolator",
                                             "compositor"}
    mosaic = validate_spec({"source": {"plugin": "simulate"}, "levels": 2}, host)
    assert plugin_configs(mosaic)["mosaic.locator"].plugin == "opencv-ecc"
    assert validate_spec({"source": {"plugin": "simulate"}, "levels": 1}, host).level_schemes == ["pairwise", "mosaic"]
    assert "mosaic.locator" not in plugin_configs(validate_spec({"source": {"plugin": "simulate"}, "levels": 1}, host))
