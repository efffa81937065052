"""report.html (self-contained, parsed), the notebook view of a RunResult, and tqdm bars without ipywidgets."""

from __future__ import annotations

import base64
import hashlib
import json
import sys
import types
import warnings
from html.parser import HTMLParser

import cv2
import numpy as np
import photonpano
import pytest
from photonpano.photons import tone_map
from photonpano.report import report_html, summary_html

SPEC = {"source": {"plugin": "simulate", "frames": 2400, "height": 128, "width": 248, "vibration_px": 2.0},
        "group_size": 300, "levels": 2}


class Page(HTMLParser):
    """Every tag with its attributes, and the text of each element with an id."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.text: dict[str, str] = {}
        self._open: list[str | None] = []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        self.tags.append((tag, attrs))
        if tag not in ("img", "meta", "br", "input"):
            self._open.append(attrs.get("id"))

    def handle_endtag(self, tag):
        if self._open:
            self._open.pop()

    def handle_data(self, data):
        for ident in self._open:
            if ident:
                self.text[ident] = self.text.get(ident, "") + data

    def img(self, ident):
        return next(attrs for tag, attrs in self.tags if tag == "img" and attrs.get("id") == ident)


def _png(src):
    assert src.startswith("data:image/png;base64,")
    return cv2.imdecode(np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8), cv2.IMREAD_UNCHANGED)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "run"
    return photonpano.run(SPEC, out_dir=out, progress=False)


def _no_external_resources(page: Page) -> None:
    for tag, attrs in page.tags:
        assert tag != "link", attrs
        for key in ("src", "href", "data", "poster", "srcset", "action"):
            value = attrs.get(key)
            assert value is None or value.startswith("data:") or value.startswith("#"), (tag, key, value[:80])
        assert not (tag == "script" and "src" in attrs)


def test_every_run_writes_a_self_contained_report(run):
    folder = run.out_dir
    text = (folder / "report.html").read_text()
    page = Page(text)
    _no_external_resources(page)
    assert "http://" not in text and "https://" not in text and "url(" not in text
    # the panorama, full size, tone-mapped as panorama.png, transparent where unobserved
    image = _png(page.img("panorama")["src"])
    pano = np.load(folder / "panorama.npy")
    assert image.shape == (*pano.shape, 4)
    assert np.array_equal(image[..., 3] > 0, np.isfinite(pano))
    assert np.abs(image[..., 0].astype(int) - tone_map(pano)).max() == 0
    # the trajectory figure is trajectory.png, inlined
    assert base64.b64decode(page.img("trajectory")["src"].split(",", 1)[1]) == (folder / "trajectory.png").read_bytes()
    summary = json.loads((folder / "run.json").read_text())
    assert page.text["status"] == summary["status"]
    shown = [line for line in page.text["warnings"].splitlines() if line.strip()]
    assert shown == (summary["warnings"] or ["none"])
    schemes = [level["scheme"] for level in summary["levels"]]
    assert sum(page.text["levels"].count(name) for name in set(schemes)) == len(schemes) == 2
    assert f"numpy{summary['versions']['numpy']}" in page.text["versions"].replace(" ", "")
    assert "simulate" in page.text["spec"] and "group_size: 300" in page.text["spec"]
    # listed in the manifest with its hash, like every output
    manifest = json.loads((folder / "manifest.json").read_text())
    assert "report.html" in manifest["files"]
    assert manifest["sha256"]["report.html"] == hashlib.sha256((folder / "report.html").read_bytes()).hexdigest()


def test_report_shows_warnings_and_degraded_status(run):
    summary = {**run.summary, "status": "degraded",
               "warnings": ["level 2: 35 % of pair registrations failed <and were bridged>", "flicker over part"]}
    page = Page(report_html(summary, run.panorama, run.homographies, run.uncertainty))
    _no_external_resources(page)
    assert page.text["status"] == "degraded"
    assert [w for w in page.text["warnings"].splitlines() if w] == summary["warnings"]  # escaped, then read back
    assert _png(page.img("trajectory")["src"]).shape[2] in (3, 4)


def test_report_inlines_a_scaled_panorama_when_huge(run, monkeypatch):
    import photonpano.report as report

    monkeypatch.setattr(report, "MAX_PANORAMA_SIDE", 100)
    image = _png(Page(report.report_html(run.summary, run.panorama, run.homographies,
                                         trajectory=b"\x89PNG")).img("panorama")["src"])
    assert max(image.shape[:2]) == 100


def test_notebook_view_is_compact(run):
    text = run._repr_html_()
    page = Page(text)
    _no_external_resources(page)
    assert page.text["status"] == run.summary["status"]
    thumb = _png(next(a for t, a in page.tags if t == "img")["src"])
    assert thumb.shape[:2] == run.panorama.shape and len(text) < 200_000  # smaller than 320 px: as it is
    small = Page(summary_html(run.summary, run.panorama, thumbnail_px=64))
    assert max(_png(next(a for t, a in small.tags if t == "img")["src"]).shape[:2]) == 64
    loaded = photonpano.load(run.out_dir)
    assert loaded._repr_html_() == text


def test_show_draws_the_panorama_outside_a_notebook(run, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = []
    monkeypatch.setattr(plt, "show", lambda: shown.append(plt.gcf()))
    run.show()
    assert len(shown) == 1 and shown[0].axes[0].images[0].get_array().shape == run.panorama.shape
    plt.close("all")


def test_a_run_without_report_writes_none(run, tmp_path):
    out = tmp_path / "run"
    photonpano.run({**SPEC, "outputs": {"report": False, "trajectory_plot": False}}, out_dir=out, progress=False)
    assert not (out / "report.html").exists()


def test_tqdm_bars_do_not_warn_without_ipywidgets(monkeypatch):
    """In a notebook without ipywidgets, tqdm.auto warns 'IProgress not found'; our bars fall back to text."""
    import importlib
    import importlib.util

    from photonpano.progress import TqdmProgress
    from tqdm.std import tqdm as text_tqdm

    class ZMQInteractiveShell:  # a Jupyter kernel's shell, as tqdm.autonotebook recognises it
        pass

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ipywidgets" else real(name, *a))
    monkeypatch.setitem(sys.modules, "ipywidgets", None)  # an import fails, as when not installed
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=ZMQInteractiveShell))
    monkeypatch.setitem(sys.modules, "ipykernel.zmqshell", types.ModuleType("ipykernel.zmqshell"))
    for name in ("tqdm.auto", "tqdm.autonotebook"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    with warnings.catch_warnings(record=True) as caught:  # the problem: tqdm.auto in this notebook
        warnings.simplefilter("always")
        importlib.import_module("tqdm.auto")
    assert any("IProgress not found" in str(w.message) for w in caught)
    for name in ("tqdm.auto", "tqdm.autonotebook"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        observer = TqdmProgress()
        observer.photonpano_progress(task="panorama", total=3, advance=0)
        observer.photonpano_progress(task="panorama", total=3, advance=3)
        observer.stop()
    assert observer._tqdm is text_tqdm
