"""Accuracy of the whole pipeline against ground truth (issue 2's acceptance, smaller case).

The full case (20 000 frames) is ``benchmarks/accuracy.py``; here 6 000 frames of the same
254x496 capture (pan 0.02 px/frame + 5 px, 30 Hz vibration at 100 kHz) with the default
spec.
"""

import pytest

from photonpano.pipeline import ground_truth_report, reconstruct
from photonpano.spec import validate_spec

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("flux, max_rmse", [(0.5, 0.3), (0.05, 0.6)])
def test_default_spec_meets_the_accuracy_bar(host, flux, max_rmse):
    spec = validate_spec({"source": {"plugin": "simulate", "frames": 6000, "flux": flux}}, host)
    source = spec.source.build()
    homographies, stats, pano, _ = reconstruct(spec, source)
    report = ground_truth_report(source, homographies, pano, spec.panorama_subbatch_px)
    rmse = [row["trajectory_rmse_px"] for row in stats]
    assert report["trajectory_rmse_px"] <= max_rmse
    assert rmse[-1] < rmse[0]
    assert report["psnr_gap_db"] <= 1.0


def test_iterating_beats_group_averaging(host):
    """Level 1 alone (group averaging + SIFT) is several times worse than three levels."""
    spec = validate_spec({"source": {"plugin": "simulate", "frames": 6000, "flux": 0.5}}, host)
    source = spec.source.build()
    _, stats, _, _ = reconstruct(spec, source)
    assert stats[0]["trajectory_rmse_px"] > 4 * stats[-1]["trajectory_rmse_px"]
