"""docs/tutorial.md holds what its commands print: figures, outputs and pictures regenerated and compared.

``docs/tutorial_generate.py --check`` reruns the tutorial's commands (about a minute) and
fails when a figure drifts beyond its tolerance, an output line changes, or a picture
no longer matches; the quick tests below check that the comparison can fail.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("tutorial_generate", ROOT / "docs" / "tutorial_generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def generator():
    return _generator()


@pytest.fixture(scope="module")
def page():
    return (ROOT / "docs" / "tutorial.md").read_text(encoding="utf-8")


def _as_printed(generator, page):
    """The figures and outputs the page shows, as if a run had produced exactly them."""
    figures = {name: float(value) for value, name in generator.FIGURE.findall(page)}
    outputs = {name: text for _, name, text, _ in generator.OUTPUT.findall(page)}
    return figures, outputs


def test_every_figure_is_marked_and_every_mark_is_a_figure(generator, page):
    marked = {name for _, name in generator.FIGURE.findall(page)}
    assert marked == set(generator.FIGURES)
    assert {name for _, name, _, _ in generator.OUTPUT.findall(page)} == set(generator.COMMANDS)
    figures, outputs = _as_printed(generator, page)
    assert generator.drifts(page, figures, outputs) == []
    assert generator.render(page, figures, outputs) == page  # rendering what the page says changes nothing


def test_a_figure_that_drifts_beyond_its_tolerance_fails(generator, page):
    figures, outputs = _as_printed(generator, page)
    within = {**figures, "psnr": figures["psnr"] + 0.9 * generator.FIGURES["psnr"][1]}
    assert generator.drifts(page, within, outputs) == []
    beyond = {**figures, "psnr": figures["psnr"] + 0.5, "group_size": figures["group_size"] + 1}
    found = generator.drifts(page, beyond, outputs)
    assert len(found) == 3  # psnr once, group_size at both of its places
    assert any(line.startswith("figure psnr (panorama PSNR") for line in found), found


def test_an_output_that_changes_fails_but_its_timings_do_not(generator, page):
    figures, outputs = _as_printed(generator, page)
    demo = outputs["demo"]
    line = next(row for row in demo.splitlines() if row.startswith("level 1:"))
    number = line.split(" inliers")[0].rsplit(" ", 1)[1]  # the median inliers
    retimed = line.rsplit(", ", 1)[0] + ", 99.9 s"
    assert generator.drifts(page, figures, {**outputs, "demo": demo.replace(line, retimed)}) == []
    changed = line.replace(f" {number} inliers", f" {2 * int(number)} inliers")
    found = generator.drifts(page, figures, {**outputs, "demo": demo.replace(line, changed)})
    assert found == [f"output of demo: {number} became {2 * int(number)} in {line!r}"]
    reworded = demo.replace("inliers", "matches", 1)
    found = generator.drifts(page, figures, {**outputs, "demo": reworded})
    assert f"output of demo: the run prints {line.replace('inliers', 'matches')!r}, the page does not" in found
    lines = demo.splitlines()
    moved = [row for row in lines if row.startswith("simulating")]
    assert moved  # stdout's note, which a pipe may deliver after stderr's level lines
    reordered = "\n\n".join(moved + [row for row in lines if row not in moved])  # nor blank lines
    assert generator.drifts(page, figures, {**outputs, "demo": reordered}) == []


def test_a_predicted_sigma_may_move_by_a_third_but_not_double(generator, page):
    """The uncertainty lines have their own tolerance (SIGMA_TOLERANCE): 0.174 -> 0.133 px passes, 2x fails."""
    figures, outputs = _as_printed(generator, page)
    text = outputs["pano"]
    line = next(row for row in text.splitlines() if row.startswith("predicted per-frame error"))
    median = line.split("median ")[1].split(" px")[0]
    for factor, drifts in ((0.77, False), (1.3, False), (2.0, True)):
        moved = line.replace(f"median {median} px", f"median {float(median) * factor:.3f} px")
        found = generator.drifts(page, figures, {**outputs, "pano": text.replace(line, moved)})
        assert bool(found) == drifts, (factor, found)


@pytest.mark.slow
def test_the_tutorial_is_what_its_commands_produce(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "docs" / "tutorial_generate.py"), "--check",
                           "--work", str(tmp_path)], capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "docs/tutorial.md is current" in done.stdout
