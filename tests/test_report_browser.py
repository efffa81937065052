"""report.html rendered by a real browser: headless Chromium, no console errors, the panorama on screen.

The browser (Debian's ``chromium``) is driven over the DevTools protocol (see
``tests/browser.py`` for why). Without a browser the tests skip, unless
``PHOTONPANO_REQUIRE_CHROMIUM=1`` (set by ``.ci/run``, which installs one): then they fail.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import photonpano
import pytest
from browser import Chromium, find_chromium
from photonpano.photons import tone_map

pytestmark = pytest.mark.slow

SPEC = {"source": {"plugin": "simulate", "frames": 2400, "height": 128, "width": 248, "vibration_px": 2.0},
        "group_size": 300, "levels": 2}
VIEWPORT = (1200, 900)


@pytest.fixture(scope="module")
def chromium():
    path = find_chromium()
    if path is None:
        if os.environ.get("PHOTONPANO_REQUIRE_CHROMIUM") == "1":
            pytest.fail("PHOTONPANO_REQUIRE_CHROMIUM=1 but no chromium on the PATH (apt-get install -y chromium)")
        pytest.skip("no chromium on the PATH (apt-get install -y chromium, or set PHOTONPANO_CHROMIUM)")
    return path


@pytest.fixture(scope="module")
def browser(chromium):
    with Chromium(chromium, *VIEWPORT) as page:
        yield page


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return photonpano.run(SPEC, out_dir=tmp_path_factory.mktemp("browser") / "run", progress=False)


def test_the_harness_sees_console_errors_and_failed_resources(browser, tmp_path):
    """The check below can fail: a page with a console error, a late exception and a missing image."""
    page = tmp_path / "broken.html"
    page.write_text("<!DOCTYPE html><html><body><img src='missing.png'><script>console.error('broken on purpose');"
                    "setTimeout(function(){null.x}, 0);</script></body></html>")
    errors = browser.open(page).errors
    assert any("broken on purpose" in e for e in errors)
    assert any(e.startswith("uncaught exception: TypeError") for e in errors)
    assert any("missing.png" in e for e in errors)


def _box(browser, element_id):
    return browser.evaluate(f"(function(){{var r=document.getElementById('{element_id}').getBoundingClientRect();"
                            "return {x:r.left+window.scrollX, y:r.top+window.scrollY, width:r.width, "
                            "height:r.height};})()")


def test_report_opens_without_console_errors_and_shows_the_panorama(browser, run):
    load = browser.open(run.out_dir / "report.html")
    assert load.errors == []
    assert not [line for line in load.console if not line.startswith(("log:", "info:", "debug:"))]
    pano = run.panorama
    # the inlined panorama decoded at full size, and every other image too
    images = browser.evaluate("Array.from(document.images).map(function(i){return [i.id, i.complete, "
                              "i.naturalWidth, i.naturalHeight];})")
    assert ["panorama", True, pano.shape[1], pano.shape[0]] in images
    assert all(complete and width > 0 for _, complete, width, _ in images), images
    assert browser.evaluate("document.getElementById('status').textContent") == run.summary["status"]

    # the screenshot of the panorama's box is the panorama: tone-mapped grey, scaled to the box
    box = _box(browser, "panorama")
    assert box["width"] > 0.8 * VIEWPORT[0] and abs(box["height"] / box["width"] - pano.shape[0] / pano.shape[1]) < 0.01
    clip = {k: float(round(v)) for k, v in box.items()}
    shot = cv2.imdecode(np.frombuffer(browser.screenshot(clip), np.uint8), cv2.IMREAD_COLOR)
    assert shot.shape[:2] == (clip["height"], clip["width"])
    grey = shot.astype(np.float64).mean(axis=2)
    size = (shot.shape[1], shot.shape[0])
    expected = cv2.resize(tone_map(pano).astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    observed = cv2.resize(np.isfinite(pano).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    observed = cv2.erode(observed, np.ones((7, 7), np.uint8)).astype(bool)  # away from the edges and seams
    assert observed.mean() > 0.3
    assert grey[observed].std() > 20  # a picture, not a blank box
    difference = np.abs(grey[observed] - expected[observed])
    assert np.median(difference) < 2 and np.percentile(difference, 95) < 8, (np.median(difference),
                                                                              np.percentile(difference, 95))
    assert np.corrcoef(grey[observed], expected[observed])[0, 1] > 0.99
    # unobserved canvas shows the page's checkerboard (grey levels 238 and 255), not black
    unobserved = cv2.erode((~np.isfinite(pano)).astype(np.uint8), np.ones((5, 5), np.uint8))
    unobserved = cv2.resize(unobserved, size, interpolation=cv2.INTER_NEAREST).astype(bool)
    if unobserved.any():
        assert grey[unobserved].min() > 200


def test_zoom_buttons_work_without_errors(browser, run):
    load = browser.open(run.out_dir / "report.html")
    natural = run.panorama.shape[1]
    fitted = _box(browser, "panorama")["width"]
    browser.evaluate("document.getElementById('zoom-1').click()")
    assert _box(browser, "panorama")["width"] == pytest.approx(natural)
    browser.evaluate("document.getElementById('zoom-in').click()")
    assert _box(browser, "panorama")["width"] == pytest.approx(2 * natural)
    browser.evaluate("document.getElementById('panorama').click()")  # back to fit
    assert _box(browser, "panorama")["width"] == pytest.approx(fitted)
    assert load.errors == []
