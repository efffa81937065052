"""The evaluation suite's quick subset (issue 26): what ``benchmarks/suite.py --quick`` checks, in CI."""

import numpy as np
import pytest
from capture_helpers import load_suite as _suite


def test_the_suite_has_forty_captures_of_ten_photographs_and_every_regime():
    suite = _suite()
    captures = suite.captures()
    assert len(captures) >= 40 and len({c.photo for c in captures}) >= 10
    variants = {c.variant for c in captures}
    assert set(suite.HARD) <= variants and set(suite.NUISANCE) <= variants
    frames = [c.source_spec()["frames"] for c in captures]
    assert min(frames) <= 6000 and max(frames) >= 100_000
    assert all(c.photo.is_file() for c in captures)
    assert {c.name for c in captures} >= set(suite.QUICK)


def test_the_stress_regimes_are_two_per_photograph_and_each_builds_a_capture():
    """``--stress``: regimes outside the yardstick, each a valid ``simulate`` spec (built, not run)."""
    from photonpano.plugins.sources.simulate import SimulateConfig

    suite = _suite()
    captures = suite.captures(stress=True)
    photos = suite.photos()
    assert len(captures) == 2 * len(photos) and {c.variant for c in captures} == set(suite.STRESS)
    for capture in captures[:len(suite.STRESS)]:
        SimulateConfig(**{k: v for k, v in capture.source_spec().items() if k != "plugin"})


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_quick_subset_status_and_uncertainty_tell_the_truth():
    """Each quick capture: degraded over 1 px, ok within 0.3 px, sigma calibrated, drizzle >= flux-canvas."""
    suite = _suite()
    rows = [suite.run_capture(c) for c in suite.captures() if c.name in suite.QUICK]
    for row in rows:
        assert "failed" not in row, row
        if row["rmse"] > 1.0:
            assert row["status"] == "degraded", row
        if row["rmse"] <= 0.3:
            assert row["status"] == "ok", row
        if row["status"] == "ok":
            assert row["within_2_sigma"] >= 0.8, row
            assert 1 / 3 <= row["sigma_median"] / row["rmse"] <= 3, row
    assert np.isfinite([r["psnr_gap"] for r in rows]).all()
    for row in rows:  # issue 27's compositor bars (measured: +0.98, +4.2, +4.0 and +0.09 dB over flux-canvas)
        assert row["over_flux_canvas"] >= -0.05 and row["over_flux_canvas_true"] >= -0.2, row


def test_seeds_run_each_capture_once_per_photon_draw(capsys):
    """``--seeds``: a capture per draw, named by it, and a line per capture with its mean and worst RMSE."""
    suite = _suite()
    assert suite.main(["--list", "--only", "city_madison/base", "--seeds", "0,3"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listed] == ["city_madison/base@seed0", "city_madison/base@seed3"]
    assert '"seed": 3' in listed[1]
    rows = [{"capture": "a/base@seed0", "rmse": 0.1}, {"capture": "a/base@seed1", "rmse": 0.3},
            {"capture": "b/dark@seed0", "failed": "locator"}]
    a, b = suite.seed_summary(rows)
    assert a.split()[0] == "a/base" and "mean RMSE 0.200" in a and "worst 0.300" in a
    assert b.startswith("b/dark") and "1 failed" in b
    with pytest.raises(SystemExit):
        suite.main(["--list", "--seeds", "one"])


def test_the_outside_check_writes_its_photographs_for_the_suite_and_overwrites_none(tmp_path):
    """``benchmarks/outside_photos.py``: one readable PNG per stem, which ``suite.py --photos`` turns into captures."""
    from capture_helpers import load_benchmark
    from PIL import Image

    outside = load_benchmark("outside_photos", "outside_photos")
    stems = ["checkerboard", "horse", "logo", "motorcycle"]
    assert outside.main([str(tmp_path), "--only", ",".join(stems)]) == 0
    images = {p.stem: np.asarray(Image.open(p)) for p in sorted(tmp_path.glob("*.png"))}
    assert sorted(images) == sorted(stems)
    assert images["horse"].dtype == np.uint8 and set(np.unique(images["horse"])) == {0, 255}  # a silhouette
    assert images["logo"].shape[2] == 3 and images["motorcycle"].shape[2] == 3  # alpha dropped; the left view
    names = [c.name for c in _suite().captures(tmp_path)]
    assert len(names) == 3 * len(stems) and "checkerboard/base" in names
    before = (tmp_path / "horse.png").read_bytes()
    assert outside.main([str(tmp_path), "--only", "horse"]) == 1  # refused: nothing overwritten
    assert (tmp_path / "horse.png").read_bytes() == before
    with pytest.raises(SystemExit):
        outside.main([str(tmp_path / "new"), "--only", "zebra"])


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_fast_pan_that_halts_over_handwriting_keeps_the_frame_s_shape():
    """A 0.06 px/frame pan halting every 6 000 frames: no keystone wander from level 1's chance perspectives.

    Level 1's locator gave 5 of 549 pairs a homography (the lowest GRIC) whose perspective
    is noise; chained, it made the keystone and scale wander by about a pixel at the frame's
    corners (0.254 px, ``ok`` with a median sigma of 0.077). With those few perspectives
    dropped (:func:`~photonpano.schemes.pairwise.drop_unsteady_perspective`): 0.067 px.
    """
    suite = _suite()
    capture = suite.Capture(suite.PHOTOS / "text_handwriting.jpg", "stop-and-go-fast", suite.STRESS["stop-and-go-fast"])
    row = suite.run_capture(capture)
    assert "failed" not in row, row
    assert row["rmse"] <= 0.12 and row["status"] == "ok", row
    assert 1 / 3 <= row["sigma_median"] / row["rmse"] <= 3, row


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_fast_pan_s_sigma_keeps_the_shape_error_its_chains_cannot_resolve():
    """The suite's fast pan (0.12 px/frame) over the coffee: its frames' shape wanders, and the sigma says so.

    A fast pan's frames far from the middle frame are tied to it only through the frames in
    between; their shape error (about 0.2 px) stays under the held-out chains' noise, so the
    shape term gave none: ``ok`` with a median sigma of 0.065, 25 % of the frames within twice
    it. The frames travel 1.45 frame widths from the middle frame, so the shape term now keeps
    the chains' standard error (:data:`~photonpano.uncertainty.UNRESOLVED_SHAPE_EXTENTS`):
    a median sigma of 0.24 px, every frame within twice it.
    """
    suite = _suite()
    capture = suite.Capture(suite.PHOTOS / "objects_coffee.jpg", "fast-pan", suite.HARD["fast-pan"])
    row = suite.run_capture(capture)
    assert "failed" not in row, row
    assert row["within_2_sigma"] >= 0.8 and 1 / 3 <= row["sigma_median"] / row["rmse"] <= 3, row
