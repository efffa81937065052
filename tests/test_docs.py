"""The documentation: generated pages up to date, the site builds in strict mode."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from photonpano import docgen
from photonpano.host import PluginHost
from photonpano.spec import OutputsConfig, spec_model

ROOT = Path(__file__).parents[1]


@pytest.mark.parametrize("page, generate", [("hooks.md", docgen.hooks_markdown),
                                            ("spec_reference.md", docgen.spec_reference_markdown)])
def test_generated_pages_are_up_to_date(page, generate):
    """The committed hooks.md and spec_reference.md equal the generator's output (no drift)."""
    committed = (ROOT / "docs" / page).read_text()
    assert committed == generate(), f"docs/{page} is stale: run python -m photonpano.docgen docs/"


def test_generated_pages_have_no_rest_markup():
    """No reST roles, double backticks, directives or raw Google section headers are left."""
    for page in ("hooks.md", "spec_reference.md"):
        text = (ROOT / "docs" / page).read_text()
        leftovers = re.findall(r":[a-z]+:`|``|^\.\. \w+::|^(?:Args|Returns|Raises):$", text, re.M)
        assert not leftovers, f"docs/{page} contains reST markup {leftovers[:3]}"


def test_spec_reference_lists_every_top_level_field():
    """Every field of the pipeline spec and of ``outputs`` has a row."""
    text = (ROOT / "docs" / "spec_reference.md").read_text()
    fields = [*spec_model(PluginHost()).model_fields, *OutputsConfig.model_fields]
    missing = [name for name in fields if f"| `{name}` |" not in text]
    assert not missing, f"docs/spec_reference.md lacks {missing}"


def test_docstring_markdown_turns_google_sections_and_roles_into_markdown():
    """Args become bullets (continuations joined), roles and literals inline code."""
    doc = '''Do a thing with :class:`~photonpano.stages.LocatorConfig`.

    Args:
        x: the ``value``, in pixels,
            continued here.
        y (int): another.

    Returns:
        A :func:`photonpano.geometry.apply` result.

    .. versionadded:: 0.1
    '''
    assert docgen.docstring_markdown(doc) == (
        "Do a thing with `LocatorConfig`.\n\n**Arguments**\n\n"
        "- `x`: the `value`, in pixels, continued here.\n- `y`: another.\n\n"
        "**Returns**\n\nA `photonpano.geometry.apply` result.\n\n*New in version 0.1.*")


def test_mkdocs_build_is_strict_clean(tmp_path):
    """``mkdocs build --strict`` succeeds without a warning (API reference included)."""
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml"),
               "--site-dir", str(tmp_path / "site")]
    result = subprocess.run(command, capture_output=True, text=True, cwd=ROOT,
                            env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    warnings = [line for line in result.stderr.splitlines() if "WARNING" in line or "ERROR" in line]
    assert result.returncode == 0 and not warnings, "\n".join(warnings) or result.stderr[-2000:]
    assert (tmp_path / "site" / "reference" / "stages" / "index.html").exists()



def test_tutorial_pictures_are_small_and_used():
    """Every picture under docs/img is under 300 KB and shown by a page (none is missing)."""
    pages = "".join(path.read_text() for path in (ROOT / "docs").glob("*.md"))
    shown = set(re.findall(r"\]\(img/([^)]+)\)", pages))
    present = {path.name: path.stat().st_size for path in (ROOT / "docs" / "img").glob("*.png")}
    assert shown == set(present), f"shown {sorted(shown)}, present {sorted(present)}"
    assert max(present.values()) < 300_000, present


MACHINE_PATH = re.compile(r"(?<![\w.:/~-])(?:/(?:work|home|tmp|Users|root|mnt|private/var)/|[A-Za-z]:\\Users\\)")
"""An absolute path of somebody's machine (``/work/...``, ``/home/...``, ``/tmp/...``,
``C:\\Users\\...``); URLs and relative paths do not match."""


def test_machine_path_pattern_finds_what_it_should():
    assert MACHINE_PATH.search("--photo /work/shared/data/x.png") and MACHINE_PATH.search("`/tmp/b15/run`")
    assert MACHINE_PATH.search("(/home/me/x)") and MACHINE_PATH.search(r"C:\Users\me\x.npy")
    assert not MACHINE_PATH.search("https://example.org/home/x and docs/tmp/x and ~/work/x and results/tmp/")


def test_docs_hold_no_absolute_paths_of_a_machine():
    """No page, docs script or the README names a path on a developer's machine."""
    files = [ROOT / "README.md", ROOT / "mkdocs.yml"] + sorted(
        p for p in (ROOT / "docs").rglob("*") if p.suffix in (".md", ".py", ".yml", ".yaml", ".txt", ".html"))
    found = [f"{path.relative_to(ROOT)}:{number}: {line.strip()[:120]}"
             for path in files for number, line in enumerate(path.read_text().splitlines(), 1)
             if MACHINE_PATH.search(line)]
    assert not found, "absolute paths of a machine in the docs:\n" + "\n".join(found)


def _nav_pages(entries) -> list[str]:
    """The page paths of an mkdocs ``nav`` (nested lists of titles -> pages or sections)."""
    pages: list[str] = []
    for entry in entries:
        values = entry.values() if isinstance(entry, dict) else [entry]
        for value in values:
            if isinstance(value, list):
                pages += _nav_pages(value)
            elif isinstance(value, str) and not value.startswith(("http://", "https://")):
                pages.append(value)
    return pages


def test_every_page_is_in_the_navigation():
    """Every Markdown page under docs/ is reachable from the site's navigation, and every nav entry exists."""
    import yaml

    nav = _nav_pages(yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"])
    pages = {str(p.relative_to(ROOT / "docs")) for p in (ROOT / "docs").rglob("*.md")}
    assert not pages - set(nav), f"pages missing from mkdocs.yml's nav: {sorted(pages - set(nav))}"
    assert not set(nav) - pages, f"nav entries without a page: {sorted(set(nav) - pages)}"
