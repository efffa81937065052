"""A third party's entry point named like a built-in: reported as a collision, the built-in keeps its name.

The entry points are injected by patching ``importlib.metadata.entry_points``: nothing is
installed into the environment.
"""

from __future__ import annotations

import importlib.metadata
import sys
import warnings
from types import SimpleNamespace

import pytest
from photonpano.host import GROUP, PluginHost
from robust import TINY, invoke, orb_locator_plugin, write_plugin

SHADOW = orb_locator_plugin("evil-sift")


class FakeEntryPoint:
    """An entry point of a distribution that is not installed (``name = value`` in ``dist``)."""

    def __init__(self, name: str, value: str, dist: str) -> None:
        self.name, self.value, self.group = name, value, GROUP
        self.dist = SimpleNamespace(name=dist, version="6.6.6")

    def load(self):
        return importlib.import_module(self.value)


@pytest.fixture
def shadowing(monkeypatch, tmp_path):
    """Entry points as if ``evil-plugins`` registered ``opencv-sift`` (and ``evil-sift``) -> module ``evil_shadow``."""
    write_plugin(tmp_path / "site", "evil_shadow", SHADOW)
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    sys.modules.pop("evil_shadow", None)
    real = importlib.metadata.entry_points
    fakes = [FakeEntryPoint("opencv-sift", "evil_shadow", "evil-plugins"),
             FakeEntryPoint("evil-sift", "evil_shadow", "evil-plugins")]

    def entry_points(**selection):
        if selection.get("group") != GROUP:
            return real(**selection)  # other callers (numba) keep the real answer
        return [*real(**selection), *fakes]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    yield
    sys.modules.pop("evil_shadow", None)


def test_the_host_keeps_the_built_in_and_records_the_collision(shadowing):
    host = PluginHost()
    assert host.registry("locator")["opencv-sift"].__module__ == "photonpano.plugins.locators.opencv_sift"
    assert "evil-sift" in host.registry("locator")  # the third party's own name still loads
    assert any("'opencv-sift' of evil-plugins (evil_shadow) is ignored" in note for note in host.collisions)


def test_plugins_lists_the_collision(shadowing):
    result = invoke("plugins")
    assert result.exit_code == 0, result.stderr
    rows = [[cell.strip() for cell in line.split("│")[1:-1]] for line in result.stdout.splitlines()
            if line.startswith("│")]
    impostor = [row for row in rows if row[0] == "opencv-sift (evil-plugins)"]
    assert len(impostor) == 1 and impostor[0][3:5] == ["evil-plugins", "6.6.6"], rows
    assert impostor[0][5].startswith("collision: entry point 'opencv-sift' of evil-plugins (evil_shadow) is")
    builtin = [row for row in rows if row[0] == "opencv-sift"]
    assert builtin == [["opencv-sift", "locator", "photonpano.plugins.locators.opencv_sift", "photonpano",
                        builtin[0][4], "ok"]], builtin


def test_validate_warns_of_the_collision(shadowing, tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: simulate\nlocator: opencv-sift\n")
    result = invoke("validate", spec)
    assert result.exit_code == 0, result.stderr
    warning = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and "'opencv-sift' of evil-plugins" in warning[0] and "ignored" in warning[0]
    assert "ratio" in result.stdout  # the built-in SIFT's fields, not the impostor's


def test_run_warns_of_the_collision_and_uses_the_built_in(shadowing, tmp_path):
    import json

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = invoke("demo", "-o", tmp_path / "out", *TINY, "--set", "levels=1")
    assert result.exit_code == 0, result.stderr
    assert any("'opencv-sift' of evil-plugins" in str(w.message) for w in caught)
    spec = json.loads((tmp_path / "out" / "run.json").read_text())["spec"]
    assert spec["locator"]["plugin"] == "opencv-sift" and "ratio" in spec["locator"]
