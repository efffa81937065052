"""Registration at a binned resolution (photonpano.budget.grid, spec `registration_binning`)."""

from __future__ import annotations

import numpy as np
import pytest


def test_bin_counts_is_the_mean_of_each_block_and_drops_the_remainder():
    from photonpano.imaging import bin_counts

    counts = np.arange(2 * 5 * 7, dtype=np.uint16).reshape(2, 5, 7)
    binned = bin_counts(counts, 2)
    assert binned.shape == (2, 2, 3) and binned.dtype == np.float32
    expected = counts[:, :4, :6].reshape(2, 2, 2, 3, 2).mean(axis=(2, 4))
    np.testing.assert_allclose(binned, expected)
    # integer block sums (the block store's compiled 2x2 path, and the general one)
    for factor in (2, 3):
        h, w = 5 // factor * factor, 7 // factor * factor
        sums = counts[:, :h, :w].reshape(2, h // factor, factor, w // factor, factor).sum(axis=(2, 4))
        np.testing.assert_array_equal(bin_counts(counts, factor, np.uint16, mean=False), sums)


def test_binned_source_keeps_the_detection_probability(tiny_capture):
    from photonpano.budget.grid import BinnedSource

    binned = BinnedSource(tiny_capture, 2)
    assert (binned.height, binned.width) == (tiny_capture.height // 2, tiny_capture.width // 2)
    edges = np.array([0, 100, 300])
    full, coarse = tiny_capture.sum_ranges(edges), binned.sum_ranges(edges)
    # the mean count of each 2x2 block, so counts / frames is still a probability
    np.testing.assert_allclose(coarse.mean(axis=(1, 2)), full.mean(axis=(1, 2)), rtol=1e-3)
    assert binned.describe()["binning"] == 2
    with pytest.raises(ValueError, match="binning"):
        BinnedSource(tiny_capture, 0)


def test_registration_grid_maps_a_binned_pixel_to_the_centre_of_its_block(tiny_capture):
    from photonpano import geometry
    from photonpano.budget.grid import RegistrationGrid

    grid = RegistrationGrid(tiny_capture, 2)
    shift = geometry.translation(3.0, -2.0)[None]
    # a shift of 3 sensor pixels is 1.5 binned pixels, and back
    np.testing.assert_allclose(grid.inward(shift)[0, :2, 2], [1.5, -1.0])
    np.testing.assert_allclose(grid.outward(grid.inward(shift)), shift, atol=1e-12)
    # binned pixel 0 covers sensor pixels 0 and 1: its centre is sensor 0.5
    to_sensor = grid.outward(np.eye(3)[None])[0]
    assert np.allclose(to_sensor, np.eye(3))
    assert RegistrationGrid(tiny_capture, 1).inward(shift) is shift


def test_auto_binning_keeps_100_pixels_on_the_short_side():
    from photonpano.budget.binnings import auto_binning

    assert auto_binning(254, 496) == 2
    assert auto_binning(256, 512) == 2
    assert auto_binning(127, 248) == 1
    assert auto_binning(199, 4000) == 1


def test_locator_lengths_are_sensor_pixels_whatever_the_binning(host):
    from photonpano.budget.grid import in_merged_pixels
    from photonpano.spec import validate_spec

    spec = validate_spec({"source": "simulate", "locator": {"plugin": "opencv-sift", "reprojection_px": 1.5}}, host)
    binned = in_merged_pixels(spec.locator, 2)
    assert binned.reprojection_px == 0.75 and binned.ecc_max_change_px == 1.0
    assert binned.max_features == spec.locator.max_features  # not a length
    assert in_merged_pixels(spec.locator, 1) is spec.locator
    orb = in_merged_pixels(validate_spec({"source": "simulate", "locator": {"plugin": "opencv-orb", "border_px": 7}},
                                         host).locator, 2)
    assert orb.border_px == 4  # integers round up


def test_a_binning_that_leaves_no_frame_is_a_one_line_error(host):
    from photonpano.errors import StageError
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.reconstruction import Stages
    from photonpano.spec import validate_spec

    spec = validate_spec({"source": "simulate", "registration_binning": 8, "group_size": 200}, host)
    with pytest.raises(StageError, match="registration_binning.*smaller than 16"):
        Stages(spec, SimulateConfig(frames=400, height=96, width=160).build())


@pytest.mark.slow
def test_binned_registration_is_as_accurate_as_full_resolution(host):
    """Levels registered on 2x2-binned merged frames track the true motion about as well (another path and size)."""
    from photonpano.executor import SerialExecutor
    from photonpano.metrics import trajectory_error
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.reconstruction import Stages
    from photonpano.spec import validate_spec

    source = SimulateConfig(frames=12000, height=220, width=360, flux=0.3, speed_px_per_frame=0.015,
                            vibration_px=3.0, seed=7).build()
    errors = {}
    for binning in (1, 2):
        spec = validate_spec({"source": "simulate", "group_size": 400, "registration_binning": binning}, host)
        stages = Stages(spec, source)
        homographies = stages.estimate_motion(SerialExecutor())
        errors[binning] = trajectory_error(homographies, source.ground_truth, source.width, source.height).rmse_px
    assert errors[2] < 0.2, errors
    assert errors[2] < 1.5 * errors[1] + 0.03, errors


def test_full_resolution_mosaic_levels_beat_binned_ones(host):
    """The mosaic levels at full resolution (the default on short captures) track better than binned 2x2."""
    from photonpano.executor import SerialExecutor
    from photonpano.metrics import trajectory_error
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.reconstruction import Stages
    from photonpano.spec import validate_spec

    source = SimulateConfig(frames=8000, height=220, width=360, flux=0.5, speed_px_per_frame=0.015,
                            vibration_px=3.0, seed=3).build()
    errors = {}
    for binning in ("auto", 2):
        spec = validate_spec({"source": "simulate", "mosaic": {"registration_binning": binning}}, host)
        stages = Stages(spec, source)
        assert (stages.budget.register_binning, stages.budget.mosaic_binning) == (2, 1 if binning == "auto" else 2)
        homographies = stages.estimate_motion(SerialExecutor())
        errors[binning] = trajectory_error(homographies, source.ground_truth, source.width, source.height).rmse_px
    assert errors["auto"] < 0.8 * errors[2], errors


def test_binned_levels_report_registrations_in_sensor_pixels(host):
    """What observers and run.json get is in sensor pixels: the pairs agree with the solved keyframes."""
    from photonpano.executor import SerialExecutor
    from photonpano.plugins.sources.simulate import SimulateConfig
    from photonpano.quality import level_figures
    from photonpano.reconstruction import Stages
    from photonpano.spec import validate_spec

    source = SimulateConfig(frames=3000, height=200, width=320, flux=0.5, vibration_px=2.0).build()
    spec = validate_spec({"source": "simulate", "group_size": 250, "levels": 2, "registration_binning": 2}, host)
    stages = Stages(spec, source)
    results = []
    stages.estimate_motion(SerialExecutor(), on_level=results.append)
    pairwise = level_figures(results[0], stages.budget.plan, source.width, source.height)
    assert pairwise["pose_graph_residual_px"] < 0.5, pairwise
    # a mosaic registration is the correction of a keyframe: sub-pixel here, not scaled by the binning
    assert level_figures(results[1], stages.budget.plan, source.width, source.height)["median_correction_px"] < 1.0


def test_block_store_reads_back_what_counting_gives(tiny_capture):
    """Photons counted once per block of frames equal the direct count of any range of whole blocks."""
    from photonpano.budget.grid import BinnedBlocks, BinnedSource
    from photonpano.executor import ThreadExecutor

    with ThreadExecutor(2) as executor:
        blocks = BinnedBlocks(tiny_capture, 2, 20, executor, chunk_blocks=7)
    try:
        stored, direct = BinnedSource(tiny_capture, 2, blocks), BinnedSource(tiny_capture, 2)
        assert stored.frame_step == 20 and blocks.n_blocks == 120
        edges = np.array([40, 60, 200, 1000, 2400])
        np.testing.assert_array_equal(stored.sum_ranges(edges), direct.sum_ranges(edges))  # integer sums: exact
        # ranges off the block grid are counted from the capture
        odd = np.array([5, 60, 75])
        assert not blocks.covers(odd)
        np.testing.assert_array_equal(stored.sum_ranges(odd), direct.sum_ranges(odd))
        # it pickles as the capture and the binning, without this process's file
        import pickle

        assert pickle.loads(pickle.dumps(stored)).blocks is None
    finally:
        blocks.close()


def test_block_size_holds_every_group_boundary():
    from photonpano.budget.grid import block_size

    assert block_size(np.arange(0, 100001, 125), 500) == 25
    assert block_size(np.arange(0, 6001, 85), 340) == 17
    assert block_size(np.array([0, 92, 185, 370]), 370) == 1  # no grid: count directly


def test_bin_counts_does_not_overflow_long_ranges():
    from photonpano.imaging import bin_counts

    counts = np.full((1, 4, 4), 60000, np.uint16)  # a range of 60 000 frames, every frame a detection
    assert bin_counts(counts, 2, mean=False)[0, 0, 0] == 240000
    assert bin_counts(counts, 2)[0, 0, 0] == 60000
