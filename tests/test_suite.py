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
