"""Hot and dead pixels found in the capture's own photon counts and inpainted (photonpano.hot_pixels).

The captures are simulated from the bundled photo (8 000 frames of 96x192, a pan with a
30 Hz vibration) with 1 % of the pixels hot; the simulator knows which
(``hot_pixel_mask``), so recall and false alarms are measured, not assumed.
"""

import numpy as np
import pytest
from capture_helpers import reconstruct_simulated
from photonpano.hot_pixels import HotPixels, find_hot_pixels, with_hot_pixels_inpainted
from photonpano.inpainting import InpaintedSource, Inpainter
from photonpano.plugins.sources.simulate import SimulateConfig

BASE = dict(frames=8000, height=96, width=192, flux=0.5, vibration_px=5.0, vibration_hz=30.0)


def _capture(**settings):
    return SimulateConfig(**{**BASE, **settings}).build()


@pytest.mark.parametrize("rate, kind", [(0.5, "hot"), (0.02, "dead")])
def test_defective_pixels_of_a_moving_capture_are_found_and_nothing_else(rate, kind):
    """Pixels firing at 0.5 are brighter than most of the scene, at 0.02 darker (stuck low)."""
    capture = _capture(hot_pixel_fraction=0.01, hot_pixel_rate=rate)
    truth = capture.hot_pixel_mask
    found = find_hot_pixels(capture)
    assert found is not None and found.moved
    assert not (found.mask & ~truth).any(), "a pixel of the scene was taken for a defect"
    # the few missed ones fire at about their scene's own rate: harmless
    assert (found.mask & truth).sum() >= 0.8 * truth.sum(), (found.mask & truth).sum()
    assert getattr(found, kind) == found.mask.sum()
    record = found.record()
    assert record["found"] == found.mask.sum() and record["scene_moved"]


@pytest.mark.slow
def test_four_percent_of_hot_pixels_are_not_taken_for_a_still_scene():
    """4 % is the share of a real SwissSPAD2 colour half array's mask (``inpaint_mask: colorspad``).

    So many raise their neighbours' 3x3 medians: a pattern in every stretch's residuals
    that, left in the test of whether the scene moved, read as a still scene (the city,
    4 000 frames of 254x496: none found) and must be left out of it (all but a few in
    clusters of more than 6).
    """
    from pathlib import Path

    photo = Path(__file__).resolve().parents[2] / "benchmarks" / "photos" / "city_madison.jpg"
    capture = SimulateConfig(photo=str(photo), frames=4000, flux=0.5, vibration_px=5.0, vibration_hz=30.0,
                             hot_pixel_fraction=0.04, hot_pixel_rate=0.5).build()
    found = find_hot_pixels(capture)
    truth = capture.hot_pixel_mask
    assert found is not None and found.moved
    assert not (found.mask & ~truth).any() and (found.mask & truth).sum() >= 0.99 * truth.sum()


def test_defects_behind_colour_filters_are_found_and_nothing_else():
    """The real SwissSPAD2 colour layout: a quarter of the pixels behind R, G or B filters.

    A filtered pixel is judged against the luminance there and its colour's ratio to the
    luminance nearby; before, only the counts with the filtered pixels inpainted were
    read: none of the defects behind a filter was found, and the filtered neighbours of
    a hot pixel, inpainted from it, were flagged (a third of the pixels flagged).
    """
    capture = _capture(cfa="colorspad", hot_pixel_fraction=0.01)
    truth, filtered = capture.hot_pixel_mask, capture.corrector.cfa >= 0
    found = find_hot_pixels(capture)
    assert found is not None and found.moved
    assert not (found.mask & ~truth).any(), "a pixel of the scene was taken for a defect"
    for where in (filtered, ~filtered):
        assert (found.mask & truth & where).sum() >= 0.9 * (truth & where).sum()
    assert not find_hot_pixels(_capture(cfa="colorspad")).mask.any()


def test_the_colour_panorama_leaves_the_defects_found_out():
    """The colour planes read the raw counts: the defects found join the sensor's missing pixels.

    True motion, the same photons with and without 1 % hot pixels (mean PSNR over R, G, B
    against the scene): the clean capture 30.2 dB, as read 18.5 dB, with the defects found
    left out 30.2 dB (before, the colour planes read every defect: as read).
    """
    from photonpano.compose import canvas_homographies
    from photonpano.metrics import colour_scene_on_canvas, psnr
    from photonpano.plugins.observers.colour_panorama import colour_panorama

    settings = dict(cfa="colorspad", frames=4000, photo=None)
    clean, hot = _capture(**settings), _capture(**settings, hot_pixel_fraction=0.01)
    to_canvas, shape = canvas_homographies(clean.ground_truth, clean.width, clean.height, 1.0)
    truth = colour_scene_on_canvas(clean, to_canvas[0] @ np.linalg.inv(clean.ground_truth[0]), shape)
    wrapped = InpaintedSource(hot, find_hot_pixels(hot).mask)
    assert wrapped.corrector.hot[hot.hot_pixel_mask].mean() > 0.9  # left out of every colour plane
    scores = {}
    for name, source in (("clean", clean), ("raw", hot), ("found", wrapped)):
        rgb = colour_panorama(source, to_canvas, shape)
        seen = np.isfinite(rgb).all(-1) & np.isfinite(truth).all(-1)
        scores[name] = np.mean([psnr(rgb[..., c], truth[..., c], seen) for c in range(3)])
    assert scores["found"] > scores["clean"] - 0.5 and scores["raw"] < scores["clean"] - 8, scores
    # the luminance, with the filtered pixels and the defects inpainted in one pass
    edges = np.array([0, 2000, 4000])
    assert abs(float(wrapped.sum_ranges(edges).mean()) / float(clean.sum_ranges(edges).mean()) - 1) < 0.01
    # the panorama stage's colour compositor reads the counts every other stage reads, and the raw ones
    from photonpano.plugins.compositors.colour import ColourPanorama
    from photonpano.plugins.compositors.drizzle import DrizzleConfig
    from photonpano.records import Canvas

    stage = ColourPanorama(DrizzleConfig().build)
    stage.prepare(Canvas(shape[0], shape[1], to_canvas), wrapped)
    both = stage.read(wrapped, edges)
    np.testing.assert_array_equal(both[0], wrapped.sum_ranges(edges))
    np.testing.assert_array_equal(both[1], hot.raw_sums(edges))


@pytest.mark.parametrize("settings", [{}, {"flux": 0.005}, {"mover_radius_px": 20.0, "mover_speed_px_per_frame": 0.08},
                                      {"flicker_hz": 120.0, "flicker_depth": 0.9, "flicker_region": "right"}])
def test_a_capture_without_defects_has_none(settings):
    """Photon noise, a dark scene, a moving disc and a lamp over half the scene are no defects."""
    found = find_hot_pixels(_capture(**settings))
    assert found is not None and found.moved and not found.mask.any()


def test_a_still_capture_flags_nothing_even_with_hot_pixels():
    """Without motion a defect and a sharp detail look alike: nothing is flagged, and the record says why."""
    still = _capture(vibration_px=0.0, speed_px_per_frame=0.0, hot_pixel_fraction=0.01)
    found = find_hot_pixels(still)
    assert found is not None and not found.moved and not found.mask.any()
    source, same = with_hot_pixels_inpainted(still, "auto")
    assert source is still and same is not None and not same.record()["scene_moved"]


def test_captures_that_cannot_be_judged_are_left_alone():
    assert find_hot_pixels(_capture(frames=20)) is None
    capture = _capture(hot_pixel_fraction=0.01)
    assert with_hot_pixels_inpainted(capture, "off") == (capture, None)


def test_inpainting_replaces_a_pixel_by_its_neighbours_mean_in_expectation():
    counts = np.zeros((400, 3, 3), np.uint16)
    counts[:, 1, 0], counts[:, 1, 2], counts[:, 0, 1], counts[:, 2, 1] = 3, 4, 4, 4  # mean 3.75
    counts[:, 1, 1] = 50
    missing = np.zeros((3, 3), bool)
    missing[1, 1] = True
    edges = np.arange(0, 401 * 10, 10)  # ranges of 10 frames
    out = Inpainter(missing).apply(counts.copy(), edges)
    assert set(np.unique(out[:, 1, 1])) == {3, 4}  # stochastic rounding of 3.75
    assert out[:, 1, 1].mean() == pytest.approx(3.75, abs=0.08)
    np.testing.assert_array_equal(out[:, ~missing], counts[:, ~missing])
    again = Inpainter(missing).apply(counts.copy(), edges)
    np.testing.assert_array_equal(again, out)  # the same ranges give the same counts
    with pytest.raises(ValueError, match="every pixel"):
        Inpainter(np.ones((2, 2), bool))


def test_an_inpainted_source_reads_as_the_capture_without_its_defects():
    capture = _capture(frames=2000, hot_pixel_fraction=0.01)
    wrapped = InpaintedSource(capture, capture.hot_pixel_mask)
    assert (wrapped.n_frames, wrapped.height, wrapped.width) == (capture.n_frames, capture.height, capture.width)
    assert wrapped.ground_truth is capture.ground_truth and wrapped.describe() == capture.describe()
    edges = np.array([0, 1000, 2000])
    raw, fixed = capture.sum_ranges(edges), wrapped.sum_ranges(edges)
    hot = capture.hot_pixel_mask
    np.testing.assert_array_equal(fixed[:, ~hot], raw[:, ~hot])
    # a hot pixel fires in half the frames; inpainted it reads like the scene around it
    assert raw[:, hot].mean() > 400 and abs(fixed[:, hot].mean() - raw[:, ~hot].mean()) < 60


@pytest.mark.slow
def test_a_default_run_inpaints_hot_pixels_and_keeps_its_trajectory():
    """1 % hot pixels pull a run toward no motion; the default run finds and inpaints them.

    The bundled office, 10 000 frames of 128x256: with them 0.057 px, and 0.075 px with
    ``hot_pixels: off`` (0.052 and 0.100 px when every mosaic level registered the
    perspective too: an affine correction is pulled less by the sensor's fixed pattern).
    """
    hot = {**BASE, "frames": 10_000, "height": 128, "width": 256, "hot_pixel_fraction": 0.01}
    error, report = reconstruct_simulated(hot)
    assert report["hot_pixels"]["found"] >= 0.95 * round(0.01 * 128 * 256), report["hot_pixels"]
    assert isinstance(report["hot_pixel_mask"], np.ndarray) and report["hot_pixel_mask"].shape == (128, 256)
    assert any("hot pixels" in note for note in report["notes"])
    off, off_report = reconstruct_simulated(hot, ["hot_pixels=off"])
    assert off_report["hot_pixels"] is None and off_report["hot_pixel_mask"] is None
    assert error.rmse_px < 0.07 and off.rmse_px > 1.2 * error.rmse_px, (error.rmse_px, off.rmse_px)


def test_hot_pixels_record_counts_hot_and_dead():
    mask = np.zeros((4, 4), bool)
    mask[1, 1] = mask[2, 3] = True
    record = HotPixels(mask, 1, 1, 8000, True).record()
    assert record == {"found": 2, "hot": 1, "dead": 1, "fraction": 0.125, "frames_read": 8000, "scene_moved": True}


def test_a_run_writes_the_pixels_it_inpainted_and_reports_them(tmp_path):
    """``hot_pixels.npy`` holds the mask ``run.json`` counts, and only defects."""
    import json

    import photonpano

    capture = {**BASE, "frames": 3000, "height": 64, "width": 128, "hot_pixel_fraction": 0.01}
    result = photonpano.run({"source": {"plugin": "simulate", **capture}, "levels": 1}, tmp_path / "out")
    summary = json.loads((tmp_path / "out" / "run.json").read_text())
    mask = np.load(tmp_path / "out" / "hot_pixels.npy")
    truth = SimulateConfig(**capture).build().hot_pixel_mask
    assert mask.dtype == bool and mask.shape == (64, 128) and summary["hot_pixels"]["found"] == mask.sum() > 0
    assert not (mask & ~truth).any() and (mask & truth).sum() >= 0.9 * truth.sum()
    assert result.summary["hot_pixels"] == summary["hot_pixels"]
    # `photonpano video` reopens the capture as the run read it
    from photonpano.errors import PhotonpanoError
    from photonpano.video import open_run

    _, reopened = open_run(tmp_path / "out")
    assert isinstance(reopened, InpaintedSource) and np.array_equal(reopened.mask, mask)
    np.save(tmp_path / "out" / "hot_pixels.npy", mask[:10])
    with pytest.raises(PhotonpanoError, match="hot_pixels.npy"):
        open_run(tmp_path / "out")
    (tmp_path / "out" / "hot_pixels.npy").write_bytes(b"not an array")
    with pytest.raises(PhotonpanoError, match="hot_pixels.npy"):
        open_run(tmp_path / "out")
