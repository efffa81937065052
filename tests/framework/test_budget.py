"""The photon budget (photonpano.budget): group_size auto, the Budget record, the pairwise scheme's binned check."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from photonpano.budget.probe import CaptureProbe, choose_group_size, plan_group_size, probe_capture
from photonpano.stages import Locator, MergedFrames, PairRegistrations


def _capture(**settings):
    from photonpano.plugins.sources.simulate import SimulateConfig

    base = {"frames": 3000, "height": 96, "width": 192, "vibration_px": 0.0}
    return SimulateConfig(**{**base, **settings}).build()


@pytest.mark.parametrize("speed", [0.02, 0.12])
def test_probe_measures_speed_and_photon_rate(speed):
    """Probe measures speed and photon rate."""
    capture = _capture(speed_px_per_frame=speed, flux=0.5)
    probe = probe_capture(capture)
    assert probe.speed_px_per_frame == pytest.approx(speed, rel=0.15)
    expected = float(capture.sum_ranges(np.array([0, capture.n_frames])).mean()) / capture.n_frames
    assert probe.photons_per_pixel_per_frame == pytest.approx(expected, rel=0.2)


def test_probe_finds_no_structure_in_uniform_photons(tmp_path):
    """Probe finds no structure in uniform photons."""
    import cv2

    photo = tmp_path / "grey.png"
    cv2.imwrite(str(photo), np.full((720, 1440, 3), 128, np.uint8))
    probe = probe_capture(_capture(photo=photo))
    assert probe.speed_px_per_frame is None
    assert max(probe.correlations) < 0.25


def test_probe_speed_is_the_scene_s_not_a_crossing_disc_s(monkeypatch):
    """A bright disc crossing a smooth scene pulls phase correlation to its own motion; the probe is not."""
    from pathlib import Path

    import photonpano.budget.probe as probe_module

    photo = Path(__file__).resolve().parents[2] / "benchmarks" / "photos" / "objects_coffee.jpg"
    scene = {"frames": 8000, "height": 128, "width": 256, "photo": str(photo), "flux": 0.5, "vibration_px": 5.0,
             "vibration_hz": 30.0}
    static = probe_capture(_capture(**scene)).speed_px_per_frame
    disc = _capture(**scene, mover_radius_px=15.0, mover_speed_px_per_frame=0.08)
    assert probe_capture(disc).speed_px_per_frame == pytest.approx(static, rel=0.15)  # 0.0263 against 0.0285
    monkeypatch.setattr(probe_module, "shift_without_mover", lambda a, b, shift, cc, limit: (shift, cc))
    assert probe_capture(disc).speed_px_per_frame > 1.5 * static  # phase correlation alone: 0.0604


def test_group_size_follows_motion_and_light():
    """Group size follows motion and light."""
    bright_slow = choose_group_size(CaptureProbe(0.2, 0.01), 20_000)
    fast = choose_group_size(CaptureProbe(0.2, 0.12), 20_000)
    dark = choose_group_size(CaptureProbe(0.0015, 0.02), 20_000)
    assert bright_slow.group_size == 500 and bright_slow.binning == 1  # the paper's typical m
    assert fast.group_size == pytest.approx(10 / 0.12, rel=0.05)  # 10 px of smear
    assert fast.blur_px == pytest.approx(10, rel=0.05)
    # dark: longer groups (twice the smear budget) and binning make up the photons
    assert 500 < dark.group_size <= 1000
    assert dark.photons_per_pixel_per_group * dark.binning ** 2 >= 10
    assert "light" in dark.reason and "motion" in fast.reason


def test_group_size_leaves_enough_groups_and_suits_short_intensity_clips():
    """Group size leaves enough groups and suits short intensity clips."""
    assert choose_group_size(CaptureProbe(0.0001, 0.01), 3000).group_size == 600  # 5 groups
    assert choose_group_size(CaptureProbe(None, None), 15).group_size == 3


def test_explicit_group_size_is_kept():
    """Explicit group size is kept."""
    plan = plan_group_size(300, source=None)
    assert (plan.group_size, plan.auto, plan.binning) == (300, False, 1)
    with pytest.raises(ValueError, match="group_size"):
        plan_group_size("big", source=None)


class _Fixed(Locator):
    """A locator returning one fixed result (ok or failed) for every pair."""

    def __init__(self, homography, ok):
        self.homography, self.ok = homography, ok

    def _register_pairs(self, merged, pairs, initial, context):
        n = len(pairs)
        return PairRegistrations(np.repeat(self.homography[None], n, 0), np.zeros(n, np.int64),
                                 np.full(n, 50, np.int64), np.full(n, self.ok))


def _noisy_pair(truth, photons_per_pixel, seed=0):
    """Two merged frames of the bundled photo at a few photons per pixel, b's pixel x at a's pixel ``truth(x)``.

    ``truth`` is a (3, 3) float64 homography (b's pixels to a's).
    """
    import cv2
    from photonpano import geometry
    from photonpano.plugins.sources.simulate import bundled_photo, load_scene

    scene = load_scene(bundled_photo(), 1440)[200:500, 400:900]
    rng = np.random.default_rng(seed)
    a = scene[50:250, 50:450]
    b = cv2.warpPerspective(scene, geometry.translation(50, 50) @ truth, (400, 200),
                            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    flux = np.stack([rng.poisson(photons_per_pixel * img / img.mean()).astype(np.float32) for img in (a, b)])
    return MergedFrames(flux=flux, frames=np.ones_like(flux), images=np.zeros(flux.shape, np.uint8),
                        masks=np.ones(flux.shape, bool))


class _Checked:
    """A locator's registrations through one level of the pairwise scheme's :class:`PairCheck`."""

    def __init__(self, locator, binning):
        from photonpano.executor import SerialExecutor
        from photonpano.schemes import PairCheck

        self.locator, self.level = locator, PairCheck(binning).start_level(SerialExecutor())

    def register_pairs(self, merged, pairs, initial):
        """Pairs of positions in ``merged``: the locator gets them as frame ids, the check as positions."""
        named = merged.frame_ids()[pairs]
        return self.level(merged, pairs, initial, self.locator.register_pairs(merged, named, initial))


def test_check_rescues_failed_pairs_and_rejects_wrong_ones():
    """The binned check rescues failed pairs and rejects wrong ones."""
    truth = np.array([[1, 0, 6.0], [0, 1, -3.0], [0, 0, 1]])
    merged = _noisy_pair(truth, photons_per_pixel=1.5)
    pairs, initial = np.array([[0, 1]]), np.eye(3)[None]
    failing = _Checked(_Fixed(np.eye(3), ok=False), binning=3)
    found = failing.register_pairs(merged, pairs, initial)
    assert found.ok[0]
    assert np.abs(found.homographies[0][:2, 2] - truth[:2, 2]).max() < 0.5
    wrong = _Checked(_Fixed(np.array([[1, 0, -40.0], [0, 1, 25.0], [0, 0, 1]]), ok=True), binning=3)
    found = wrong.register_pairs(merged, pairs, initial)
    stats = wrong.level.figures()
    assert stats["rejected_by_check"] == 1 and stats["rescued"] == 1 and stats["binning"] == 3
    assert np.abs(found.homographies[0][:2, 2] - truth[:2, 2]).max() < 0.5


@pytest.mark.parametrize("case", ["translation, estimate sheared", "rotation, estimate the identity"])
def test_a_direct_registration_takes_the_translation_where_the_estimates_shape_is_wrong(case):
    """The rescue's translation fits a translated pair whose estimate is misshapen; a rotated pair keeps the affine.

    Six photon draws at 1 photon per pixel: the pair shifted by (6, -3) px from an
    estimate scaled 2 % and sheared 1.5 % registers to 0.12 px mean corner error (0.28
    with the affine correction of the estimate alone); the pair rotated by 3 degrees from
    the identity to 0.20 px (a translation would leave 10 px).
    """
    from photonpano import geometry
    from photonpano.imaging import binned_frame, register_binned

    w, h = 400, 200
    if case.startswith("translation"):
        truth = geometry.translation(6, -3)
        initial = truth @ geometry.from_centre(np.array([[1.02, 0.015, 0], [0, 0.99, 0], [0, 0, 1]]), w, h)
    else:
        c, s = np.cos(0.05), np.sin(0.05)
        truth, initial = geometry.from_centre(np.array([[c, -s, 4], [s, c, 2], [0, 0, 1]]), w, h), np.eye(3)
    errors = []
    for seed in range(6):
        merged = _noisy_pair(truth, 1.0, seed)
        a, b = (binned_frame(merged.flux[i], merged.masks[i], 2) for i in (0, 1))
        found, correlation, overlap = register_binned(a, b, initial, 2)
        assert correlation > 0.5 and overlap > 0.8 * a[0].size
        errors.append(geometry.mean_corner_distance(found[None], truth[None], w, h)[0])
    assert np.mean(errors) < (0.18 if case.startswith("translation") else 0.3)


@pytest.mark.parametrize("case, expected", [("one axis scaling", "translation"), ("independent noise", "per pair"),
                                            ("a turn with one axis scaling", "per pair"),
                                            ("a steady zoom", "per pair")])
def test_a_level_s_rescues_take_translations_only_where_they_scale_one_axis_without_turning(case, expected):
    """rescue_motion: one axis scaling alone -> translations; noise, a turn or a zoom of both axes -> kept.

    200 rescues, shapes in pixels at the frame's half width with unit noise. One axis
    scaling ramps the vertical scale (zoom and anisotropy alike, as on the checkerboard);
    the turn adds a sine of 1 px over noise of 0.5 to it; the zoom is 0.5 px per pair.
    """
    from photonpano.schemes.check import rescue_motion

    rng = np.random.default_rng(3)
    shapes = rng.normal(0.0, 1.0, (200, 4))
    ramp = np.linspace(-1.0, 1.0, 200)
    if "one axis" in case:
        shapes[:, 1] += -2.0 + ramp
        shapes[:, 2] = shapes[:, 1] + rng.normal(0.0, 0.1, 200)
    if "turn" in case:
        shapes[:, 0] = 0.5 * shapes[:, 0] + np.sin(3 * np.pi * ramp)
    if case == "a steady zoom":
        shapes[:, 1] += 0.5
    motion, figures = rescue_motion(shapes)
    assert motion == expected, figures
    assert set(figures) == {"rotation", "zoom", "anisotropy"}


@pytest.mark.parametrize("rescues", [12, 6])
def test_a_level_settled_for_translations_gives_each_rescue_its_translation(rescues, monkeypatch):
    """settle(): the level's decision reaches the right pairs of the right calls, and the figures.

    Pairs shifted by (6, -3) px from an estimate that knows it, their locator failing,
    one pair per call; the decision is forced to ``"translation"``. With 12 rescues (at
    least SETTLE_MIN_RESCUES) every rescue ends a translation of the estimate within
    0.5 px of the truth, its correlation in the level's figures; with 6 the level keeps
    them as they are and decides nothing.
    """
    from photonpano.executor import SerialExecutor
    from photonpano.schemes import PairCheck, check
    from photonpano.schemes.check import SETTLE_MIN_RESCUES

    shapes = []
    monkeypatch.setattr(check, "rescue_motion", lambda s: (shapes.append(s), ("translation", {}))[1])
    truth = np.array([[1, 0, 6.0], [0, 1, -3.0], [0, 0, 1]])
    level = PairCheck(2).start_level(SerialExecutor())
    calls = []
    for seed in range(rescues):
        merged = _noisy_pair(truth, 1.0, seed)
        failed = _Fixed(np.eye(3), ok=False).register_pairs(merged, merged.frame_ids()[np.array([[0, 1]])],
                                                            truth[None])
        calls.append(level(merged, np.array([[0, 1]]), truth[None], failed))
    assert all(found.ok[0] for found in calls) and level.figures()["rescued"] == rescues
    settled = level.settle(calls)
    figures = level.figures()
    if rescues < SETTLE_MIN_RESCUES:
        assert settled is calls and figures["rescue_motion"] is None and not shapes
        return
    assert figures["rescue_motion"] == "translation" and shapes[0].shape == (rescues, 4)
    homographies = np.concatenate([found.homographies for found in settled])
    assert np.abs(homographies[:, :2, :2] - np.eye(2)).max() < 1e-9  # translations of the estimate
    assert np.abs(homographies[:, :2, 2] - truth[:2, 2]).max() < 0.5
    assert all(found.ok[0] for found in settled)
    assert figures["median_correlation"] == pytest.approx(np.median(level.correlations))
    assert min(level.correlations) > 0.4


def test_a_level_whose_rescues_tilt_steadily_keeps_their_perspective():
    """settle(): rescues whose homography refinements add a steady keystone of over 1 px take those homographies.

    As a camera on a tripod turns: each pair shifted by (6, -3) px with a keystone of 2-4 px
    at the frame's corners (``p7``), the estimate the shift alone, the locator failing. The
    affine rescues cannot hold the keystone (their corners 1 px off or more); the level
    decides ``"perspective"`` and each rescue ends within 0.5 px of the truth.
    """
    from photonpano import geometry
    from photonpano.executor import SerialExecutor
    from photonpano.schemes import PairCheck

    w, h = 400, 200
    level = PairCheck(2).start_level(SerialExecutor())
    calls, truths = [], []
    for seed, keystone_px in enumerate(np.linspace(2.0, 4.0, 12)):
        truth = geometry.from_centre(np.array([[1, 0, 6.0], [0, 1, -3.0], [keystone_px / ((w - 1) / 2) ** 2, 0, 1]]),
                                     w, h)
        merged = _noisy_pair(truth, 2.0, seed)
        initial = geometry.translation(6.0, -3.0)
        failed = _Fixed(np.eye(3), ok=False).register_pairs(merged, merged.frame_ids()[np.array([[0, 1]])],
                                                            initial[None])
        calls.append(level(merged, np.array([[0, 1]]), initial[None], failed))
        truths.append(truth)
    affine = np.concatenate([found.homographies for found in calls])
    assert np.median(geometry.mean_corner_distance(affine, np.stack(truths), w, h)) > 1.0
    settled = level.settle(calls)
    figures = level.figures()
    assert figures["rescue_motion"] == "perspective", figures
    assert figures["rescue_shapes"]["horizontal"]["median_px"] >= 1.0
    kept = np.concatenate([found.homographies for found in settled])
    assert geometry.mean_corner_distance(kept, np.stack(truths), w, h).max() < 0.5


def test_a_level_whose_sampled_refinements_rule_a_turn_out_refines_no_other_rescue(monkeypatch):
    """settle(): a quarter of the rescues refined by a homography shows no keystone: the others are not refined.

    44 rescues of pairs shifted by (6, -3) px, no perspective, the locator failing: the
    sample of every REFINE_SAMPLE-th rescue (11, REFINE_SAMPLE_MIN set to 10 for the test)
    is refined, its median keystone stays under KEYSTONE_RULED_OUT_PX, and the level ends
    as it does with every rescue refined (the same registrations and figures, not
    ``"perspective"``).
    """
    from photonpano import imaging
    from photonpano.executor import SerialExecutor
    from photonpano.schemes import PairCheck, check

    truth = np.array([[1, 0, 6.0], [0, 1, -3.0], [0, 0, 1]])
    pairs = [_noisy_pair(truth, 2.0, seed) for seed in range(44)]
    refined = []
    monkeypatch.setattr(check, "REFINE_SAMPLE_MIN", 10)
    monkeypatch.setattr(check, "refine_binned_homography",
                        lambda *args, **kw: (refined.append(1), imaging.refine_binned_homography(*args, **kw))[1])

    def settled(ruled_out_px):
        monkeypatch.setattr(check, "KEYSTONE_RULED_OUT_PX", ruled_out_px)
        refined.clear()
        level = PairCheck(2).start_level(SerialExecutor())
        calls = [level(merged, np.array([[0, 1]]), truth[None],
                       _Fixed(np.eye(3), ok=False).register_pairs(merged, merged.frame_ids()[np.array([[0, 1]])],
                                                                  truth[None])) for merged in pairs]
        found = level.settle(calls)
        return np.concatenate([f.homographies for f in found]), level.figures(), len(refined)

    sampled, figures, count = settled(check.KEYSTONE_RULED_OUT_PX)
    every, every_figures, every_count = settled(0.0)  # nothing ruled out: every rescue refined
    assert count == 11 and every_count == 44
    assert figures["rescue_motion"] != "perspective" and figures == every_figures
    np.testing.assert_array_equal(sampled, every)


def _keystoned(keystone_px: NDArray[np.float64], w: int, h: int, seed: int) -> NDArray[np.float64]:
    """Pair registrations shifted by about (10, 2) px with keystones ``p7`` of ``keystone_px`` at the corner."""
    from photonpano import geometry

    rng = np.random.default_rng(seed)
    found = np.tile(np.eye(3), (len(keystone_px), 1, 1))
    found[:, 0, 2], found[:, 1, 2] = rng.normal(10.0, 1.0, len(found)), rng.normal(2.0, 1.0, len(found))
    found[:, 2, 0] = keystone_px / ((w - 1) / 2) ** 2
    return geometry.from_centre(found, w, h)


def test_a_level_s_pairs_drop_the_few_perspectives_their_locator_gave_by_chance():
    """drop_unsteady_perspective: a few noisy keystones go; most pairs with one, or a steady one, stay.

    6 of 60 pairs with a keystone of 0.3 px of noise (a locator choosing each pair's model
    where the camera does not turn): each registered pair among them becomes the affine map
    nearest its homography over the frame; the others, and failed pairs, stay as they were. 20 of 60 (a turning
    camera's share), or all 60 with 2-4 px of one sign (a tripod pan): the same
    registrations come back.
    """
    from photonpano import geometry
    from photonpano.schemes.check import SETTLE_MIN_RESCUES
    from photonpano.schemes.pairwise import drop_unsteady_perspective

    w, h = 248, 127
    rng = np.random.default_rng(3)
    chance = np.where(np.arange(60) % 10 == 1, rng.normal(0.0, 0.3, 60), 0.0)
    noisy = _keystoned(chance, w, h, 0)
    ok = np.arange(60) % 20 != 0
    calls = [PairRegistrations(noisy[k:k + 20], np.zeros(20, np.int64), np.full(20, 40), ok[k:k + 20])
             for k in (0, 20, 40)]
    flattened, figures = drop_unsteady_perspective(calls, w, h)
    assert figures is not None and not figures["kept"], figures
    assert figures["pairs"] == 57 and figures["with_perspective"] == 6 and figures["horizontal"] is None
    after = np.concatenate([found.homographies for found in flattened])
    assert np.abs(after[ok, 2, :2]).max() == 0 and np.array_equal(after[~ok], noisy[~ok])
    affine = ok & (chance == 0)
    assert np.array_equal(after[affine], noisy[affine])
    grid = geometry.pixel_grid(w, h, 4)  # each affine is the least-squares fit to its homography there
    design = np.column_stack([grid, np.ones(len(grid))])
    np.testing.assert_allclose(after[1, :2], np.linalg.lstsq(design, geometry.apply(noisy[1], grid))[0].T, atol=1e-9)
    assert geometry.mean_corner_distance(after[ok], noisy[ok], w, h).max() < 1.0

    turning = _keystoned(np.where(np.arange(60) % 3 == 0, rng.normal(0.0, 0.3, 60), 0.0), w, h, 1)
    steady = _keystoned(np.linspace(2.0, 4.0, 60), w, h, 2)
    for kind in (turning, steady):
        calls = [PairRegistrations(kind, np.zeros(60, np.int64), np.full(60, 40), np.ones(60, bool))]
        kept, figures = drop_unsteady_perspective(calls, w, h)
        assert figures is not None and figures["kept"], figures
        assert kept[0] is calls[0]
    assert figures["horizontal"]["signal"] and figures["horizontal"]["median_px"] >= 1.0
    few = [PairRegistrations(noisy[:SETTLE_MIN_RESCUES - 1], np.zeros(SETTLE_MIN_RESCUES - 1, np.int64),
                             np.full(SETTLE_MIN_RESCUES - 1, 40), np.ones(SETTLE_MIN_RESCUES - 1, bool))]
    assert drop_unsteady_perspective(few, w, h) == (few, None)


def test_check_flags_pure_noise():
    """The binned check flags pure noise."""
    rng = np.random.default_rng(1)
    flux = rng.poisson(2.0, (2, 200, 400)).astype(np.float32)
    merged = MergedFrames(flux=flux, frames=np.ones_like(flux), images=np.zeros(flux.shape, np.uint8),
                          masks=np.ones(flux.shape, bool))
    checked = _Checked(_Fixed(np.eye(3), ok=True), binning=3)
    assert not checked.register_pairs(merged, np.array([[0, 1]]), np.eye(3)[None]).ok[0]


def test_binned_check_maps_homographies_to_binned_pixels_exactly():
    """Binned frame b warped by the binned homography equals binned frame a (the pixel-centre convention).

    On a linear ramp both sides are exact up to OpenCV's 1/32-pixel interpolation steps:
    binning averages a block to the value at its centre, and bilinear interpolation of
    a linear function is exact. A map off by the binned pixels' centre offset (the bug
    this pins) is 0.13 / 0.32 ramp units off at binning 2 / 4.
    """
    import cv2
    from photonpano import geometry
    from photonpano.imaging import _warp, block_mean, in_binned_pixels

    yy, xx = np.mgrid[0:240, 0:320].astype(np.float32)
    scene = xx + 0.5 * yy  # frame b
    angle, zoom = np.deg2rad(8.0), 1.15
    h = geometry.translation(20.0, -10.0) @ np.array([[zoom * np.cos(angle), -zoom * np.sin(angle), 0],
                                                      [zoom * np.sin(angle), zoom * np.cos(angle), 0], [0, 0, 1]])
    moved = cv2.warpPerspective(scene, h, (320, 240), flags=cv2.INTER_LINEAR)  # frame a: b's pixels mapped by h
    for factor in (2, 4):
        a, valid_a = block_mean(moved, factor, moved > 0)
        b, valid_b = block_mean(scene, factor)
        warped, inside = _warp(b, valid_b, in_binned_pixels(h, factor))
        core = inside & valid_a
        core[:2], core[-2:], core[:, :2], core[:, -2:] = False, False, False, False
        assert np.abs(warped - a)[core].mean() < 0.06, factor


def test_check_bins_each_frame_once_across_calls_and_drops_frames_no_longer_used(monkeypatch):
    """A frame used by consecutive calls is binned once (by content id, or digest without ids)."""
    from photonpano.schemes import check

    merged = _noisy_pair(np.array([[1, 0, 6.0], [0, 1, -3.0], [0, 0, 1]]), photons_per_pixel=1.5)
    binned = []
    original = check.binned_frame
    monkeypatch.setattr(check, "binned_frame", lambda *a, **k: binned.append(1) or original(*a, **k))
    checked = _Checked(_Fixed(np.array([[1, 0, 6.0], [0, 1, -3.0], [0, 0, 1]]), ok=True), binning=3)
    pairs, initial = np.array([[0, 1]]), np.eye(3)[None]
    first = checked.register_pairs(merged, pairs, initial)
    assert len(binned) == 2
    again = checked.register_pairs(merged, pairs, initial)  # same content, no ids: digests match
    assert len(binned) == 2
    np.testing.assert_array_equal(first.homographies, again.homographies)
    with_ids = MergedFrames(merged.flux, merged.frames, merged.images, merged.masks, ids=MergedFrames.new_ids(2))
    checked.register_pairs(with_ids, pairs, initial)  # ids are other keys: binned anew, old entries dropped
    checked.register_pairs(with_ids, np.array([[1, 0]]), initial)
    assert len(binned) == 4 and len(checked.level._binned) == 2
    renewed = MergedFrames(merged.flux, merged.frames, merged.images, merged.masks, ids=MergedFrames.new_ids(2))
    checked.register_pairs(renewed, pairs, initial)  # same pixels, new ids: the producer says new content
    assert len(binned) == 6
    checked = _Checked(checked.locator, binning=3)  # the next level starts its own check: nothing is kept
    assert not checked.level._binned
    masked = merged.masks.copy()
    masked[1, :20] = False  # same flux, another mask: another binned frame
    checked.register_pairs(MergedFrames(merged.flux, merged.frames, merged.images, merged.masks), pairs, initial)
    checked.register_pairs(MergedFrames(merged.flux, merged.frames, merged.images, masked), pairs, initial)
    assert len(binned) == 6 + 2 + 1


def _budget(source, **spec):
    from photonpano.budget import Budget
    from photonpano.host import PluginHost
    from photonpano.spec import validate_spec

    return Budget.for_capture(validate_spec({"source": "simulate", **spec}, PluginHost()), source)


def test_budget_of_a_dark_capture_bins_the_check_and_the_agreement_and_says_why():
    """group_size auto in the dark: longer groups, a binned check, a coarser agreement; each with its reason."""
    import dataclasses

    budget = _budget(_capture(flux=0.02, speed_px_per_frame=0.02), registration_binning=1)
    plan = budget.plan
    assert plan.auto and budget.group_size == plan.group_size > 500  # the light, not the typical m, set it
    assert budget.register_binning == 1 and budget.register_reason == "set in the spec"
    assert budget.check_binning == max(2, plan.binning)  # in merged-frame pixels = sensor pixels at k = 1
    # about 20 photons per binned pixel: the agreement's blocks grow as the light falls
    per_group = plan.photons_per_pixel_per_group
    assert per_group * budget.agreement_binning ** 2 >= 20 > per_group * (budget.agreement_binning - 1) ** 2
    record = budget.record()
    assert record["check_binning"] == budget.check_binning and record["reasons"]["group_size"] == plan.reason
    assert "light" in plan.reason and f"{budget.agreement_binning}x{budget.agreement_binning}" in \
        record["reasons"]["agreement_binning"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        budget.check_binning = 1


def test_budget_with_an_explicit_group_size_runs_no_check_and_counts_the_check_in_merged_pixels():
    """An explicit m keeps the plain locator; with auto the check's blocks are counted in merged-frame pixels."""
    from photonpano.budget import check_binning
    from photonpano.budget.probe import GroupPlan

    explicit = _budget(_capture(frames=1000), group_size=200, registration_binning=2)
    assert (explicit.group_size, explicit.check_binning, explicit.register_binning) == (200, None, 2)
    assert "not checked" in explicit.check_reason
    auto = GroupPlan(300, binning=6, auto=True)
    assert [check_binning(auto, k) for k in (1, 2, 3, 4)] == [6, 3, 2, 2]  # round(6 / k), blocks of >= 2 sensor px
    assert check_binning(GroupPlan(300, auto=True), 4) == 1


def test_mosaic_levels_register_at_full_resolution_on_short_well_lit_captures(monkeypatch):
    """mosaic.registration_binning auto: 1 within the pixel-frame and light limits, else level 1's binning."""
    from photonpano.budget import binnings as grid

    capture = _capture(frames=1000, height=224, width=320)  # 7.2e7 pixel-frames, binned 2x2 at level 1
    auto = _budget(capture, group_size=200)
    assert auto.plan.photons_per_pixel_per_group >= grid.FULL_RESOLUTION_MOSAIC_PHOTONS
    assert (auto.register_binning, auto.mosaic_binning) == (2, 1)
    assert "full resolution" in auto.mosaic_reason and auto.record()["mosaic_binning"] == 1
    assert auto.record()["reasons"]["mosaic_binning"] == auto.mosaic_reason
    dim = _budget(capture, group_size=20)  # a tenth of the photons per group
    assert dim.mosaic_binning == 2 and "photons per pixel per group, under 10" in dim.mosaic_reason
    monkeypatch.setattr(grid, "FULL_RESOLUTION_MOSAIC_MAX", 7e7)  # a longer capture, in effect
    long = _budget(capture, group_size=200)
    assert long.mosaic_binning == 2 and "pixel-frames exceed" in long.mosaic_reason
    monkeypatch.undo()
    assert _budget(capture, group_size=200, registration_binning=2).mosaic_binning == 2  # one binning, as set
    assert _budget(capture, group_size=200, mosaic={"registration_binning": 3}).mosaic_binning == 3


def test_a_degraded_run_whose_mosaic_was_binned_for_its_length_alone_is_told_of_full_resolution(monkeypatch):
    """The note names mosaic.registration_binning: 1 where auto binned for length, and only on a degraded run."""
    from photonpano import quality
    from photonpano.budget import binnings
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.spec import validate_spec

    capture = _capture(frames=1000, height=224, width=320)  # 7.2e7 pixel-frames, binned 2x2 at level 1

    def spec(**settings):
        return validate_spec({"source": "simulate", "group_size": 200, **settings}, PluginHost())

    def hint(binning=2, light=100.0, **settings):
        return binnings.full_resolution_hint(spec(**settings), capture, binning, light)

    assert hint() is None  # within the pixel-frame limit: auto registers at full resolution
    monkeypatch.setattr(binnings, "FULL_RESOLUTION_MOSAIC_MAX", 7e7)  # a longer capture, in effect
    assert "mosaic.registration_binning: 1" in hint() and "binned 2x2" in hint()
    assert hint(light=None) is not None  # intensity frames: light never binds
    assert hint(light=5.0) is None  # binned for light: full resolution would be noisier
    assert hint(binning=1, mosaic={"registration_binning": 1}) is None
    assert hint(mosaic={"registration_binning": 2}) is None and hint(registration_binning=2) is None

    def run(status):
        monkeypatch.setattr(quality, "assess", lambda *args, **kwargs: (status, []))
        report = {}
        reconstruct(spec(levels=2), capture, report=report)
        return report["notes"]

    assert any("mosaic.registration_binning: 1" in note for note in run("degraded"))
    assert not any("registration_binning" in note for note in run("ok"))


def test_a_long_capture_whose_binned_mosaic_leaves_frames_over_the_limit_runs_it_again_at_full_resolution(
        monkeypatch):
    """Frames predicted above the limit after binned mosaic levels: levels 2.. again at full resolution from level 1."""
    from photonpano import uncertainty
    from photonpano.budget import binnings
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.spec import validate_spec

    capture = _capture(frames=1000, height=224, width=320)  # 7.2e7 pixel-frames, binned 2x2 at level 1
    spec = validate_spec({"source": "simulate", "group_size": 200, "levels": 2}, PluginHost())
    monkeypatch.setattr(binnings, "FULL_RESOLUTION_MOSAIC_MAX", 7e7)  # a longer capture, in effect
    real = uncertainty.frame_uncertainty

    def run(predicted_px):
        calls, seen = [], []

        def predicted(*args, **kwargs):  # the binned run's prediction (the first), then the real ones
            found = real(*args, **kwargs)
            calls.append(len(calls))
            if len(calls) > 1 or predicted_px is None:
                return found
            over = {"frames": [0, 10], "seconds": [0.0, 1e-4], "max_px": predicted_px}

            class Over:  # the uncertainty found, with one range predicted over the limit
                def summary(self, *a, **k):
                    return {**found.summary(*a, **k), "above_limit": [over]}

            return Over()

        monkeypatch.setattr(uncertainty, "frame_uncertainty", predicted)
        report, done = {}, {}

        def progress(task, total):  # each task name's bar: its total and the units reported done
            done.setdefault(task, [total, 0])  # as the bars: one per task name
            return lambda n: done[task].__setitem__(1, done[task][1] + n)

        _, stats, _, _ = reconstruct(spec, capture, report=report, on_level=lambda level: seen.append(level.level),
                                     progress=progress)
        assert all(units <= total for total, units in done.values()), done  # no bar counts a level twice
        return report, [row["level"] for row in stats], seen

    report, levels, seen = run(2.5)
    budget = report["budget"]
    assert budget["mosaic_binning"] == 1 and "registered again" in budget["reasons"]["mosaic_binning"]
    assert any("ran again at full resolution" in note and "2.5 px" in note for note in report["notes"])
    assert levels == [1, 2] and seen == [1, 2, 2]  # the statistics once per level; observers see both runs
    report, levels, seen = run(None)  # nothing predicted above the limit: binned, once
    assert report["budget"]["mosaic_binning"] == 2 and levels == [1, 2] and seen == [1, 2]


def test_a_long_capture_whose_binned_mosaic_registers_nothing_runs_it_again_at_full_resolution(monkeypatch):
    """A binned mosaic level that registered none of its frames: the levels again at full resolution, not a failure.

    Where the spec binned the mosaic levels itself, or they failed at full resolution, the
    StageError stands.
    """
    from photonpano.budget import binnings
    from photonpano.errors import StageError
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.schemes.mosaic import MosaicScheme
    from photonpano.spec import validate_spec

    capture = _capture(frames=1000, height=224, width=320)  # 7.2e7 pixel-frames, binned 2x2 at level 1
    monkeypatch.setattr(binnings, "FULL_RESOLUTION_MOSAIC_MAX", 7e7)  # a longer capture, in effect
    real = MosaicScheme.locate
    failing_widths: set[int] = set()

    def locate(self, task):  # registers nothing on frames of the failing widths (the binned capture's)
        if task.source.width in failing_widths:
            raise StageError("locator", "mosaic", f"level {task.level}: none of the 5 merged frames registered")
        return real(self, task)

    monkeypatch.setattr(MosaicScheme, "locate", locate)

    def run(**mosaic):
        spec = validate_spec({"source": "simulate", "group_size": 200, "levels": 2, "mosaic": mosaic}, PluginHost())
        report, seen = {}, []
        homographies, stats, _, _ = reconstruct(spec, capture, report=report, on_level=lambda r: seen.append(r.level))
        return homographies, report, seen, [row["level"] for row in stats]

    failing_widths.add(160)
    homographies, report, seen, levels = run()
    assert report["budget"]["mosaic_binning"] == 1 and levels == [1, 2] and seen == [1, 2]
    assert "none of the 5 merged frames" in report["budget"]["reasons"]["mosaic_binning"]
    assert any("failed (level 2: none of the 5" in note and "ran again at full resolution" in note
               for note in report["notes"])
    failing_widths.clear()
    np.testing.assert_allclose(homographies, run(registration_binning=1)[0], atol=1e-9)
    failing_widths.add(160)
    with pytest.raises(StageError, match="none of the 5"):  # binned by the spec: its choice stands
        run(registration_binning=2)
    failing_widths.add(320)
    with pytest.raises(StageError, match="none of the 5"):  # at full resolution too: nothing left to try
        run()


def test_a_long_capture_whose_level_one_features_failed_registers_its_mosaic_at_full_resolution_at_once(
        monkeypatch):
    """Level 1 rescued (nearly) every pair: the mosaic levels run at full resolution from level 2, once.

    The trajectory is the one the spec's ``mosaic.registration_binning: 1`` gives, and
    where level 1's features did not fail the one of ``mosaic.registration_binning: 2``.
    """
    from photonpano.budget import binnings
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.spec import validate_spec

    capture = _capture(frames=1000, height=224, width=320)  # 7.2e7 pixel-frames, binned 2x2 at level 1
    monkeypatch.setattr(binnings, "FULL_RESOLUTION_MOSAIC_MAX", 7e7)  # a longer capture, in effect

    def run(rescued_fraction, **mosaic):
        monkeypatch.setattr(binnings, "LITTLE_TEXTURE_RESCUED", rescued_fraction)
        spec = validate_spec({"source": "simulate", "group_size": 200, "levels": 2, "mosaic": mosaic}, PluginHost())
        report, seen = {}, []
        homographies, _, _, _ = reconstruct(spec, capture, report=report, on_level=lambda r: seen.append(r.level))
        return homographies, report, seen

    at_once, report, seen = run(0.0)  # every level 1 counts as one whose features failed
    assert seen == [1, 2] and report["budget"]["mosaic_binning"] == 1
    assert "features failed" in report["budget"]["reasons"]["mosaic_binning"]
    assert any("features failed" in note for note in report["notes"])
    assert not any("ran again" in note for note in report["notes"])
    np.testing.assert_allclose(at_once, run(0.0, registration_binning=1)[0], atol=1e-9)
    binned, report, seen = run(1.01)  # none does: binned
    assert seen == [1, 2] and report["budget"]["mosaic_binning"] == 2
    np.testing.assert_allclose(binned, run(1.01, registration_binning=2)[0], atol=1e-9)


def test_an_explicit_group_size_short_of_light_gets_a_note_naming_the_budgets_choice():
    """An explicit m gathering clearly fewer photons than the budget wants is noted; enough light is not."""
    from photonpano.budget.probe import short_of_light

    dark = _capture(flux=0.02, speed_px_per_frame=0.02)
    note = short_of_light(plan_group_size(200, dark), dark.n_frames)
    auto = choose_group_size(probe_capture(dark), dark.n_frames)
    assert note is not None and "group size 200" in note and f"would choose {auto.group_size}" in note
    assert short_of_light(plan_group_size(int(auto.group_size * 0.9), dark), dark.n_frames) is None
    bright = _capture(flux=0.5)
    assert short_of_light(plan_group_size(200, bright), bright.n_frames) is None
    assert short_of_light(auto, dark.n_frames) is None


def test_probe_finds_a_vibration_and_its_period_but_not_in_a_pan():
    """The velocity spectrum of consecutive blocks gives a vibration's period (and none for a steady pan)."""
    vibrating = probe_capture(_capture(frames=12_000, flux=0.5, speed_px_per_frame=0.006, vibration_px=4.0,
                                       vibration_hz=45.0))
    assert vibrating.vibration_period_frames == pytest.approx(100_000 / 45, rel=0.12)
    assert 2.0 <= vibrating.vibration_px <= 8.0
    steady = probe_capture(_capture(frames=12_000, flux=0.5, speed_px_per_frame=0.02))
    assert steady.vibration_period_frames is None and steady.vibration_px is None


def test_group_size_samples_a_vibration_three_times_per_period():
    """Level 1 keeps at least three groups per vibration period, in the dark as in daylight."""
    dark = CaptureProbe(0.0075, 0.0135)
    free = choose_group_size(dark, 100_000)
    assert free.group_size == 1300  # light: up to twice the smear budget
    shaken = choose_group_size(CaptureProbe(0.0075, 0.0135, vibration_period_frames=2350.0, vibration_px=4.1),
                               100_000)
    assert shaken.group_size == 780 and "vibration every 2350 frames" in shaken.reason
    assert shaken.binning >= free.binning  # binning makes up the photons the shorter groups lose
    slow = choose_group_size(CaptureProbe(0.2, 0.01, vibration_period_frames=3333.0, vibration_px=5.0), 20_000)
    assert slow.group_size == 500 and "vibration" not in slow.reason  # 6.7 groups per period already


def test_when_no_pair_registers_with_an_explicit_group_size_the_error_says_auto_would_check_them(tmp_path):
    """A plain wall defeats SIFT: with m set in the spec the error names it and what ``auto`` does instead."""
    import cv2
    import photonpano
    from photonpano.errors import StageError

    photo = tmp_path / "wall.png"
    cv2.imwrite(str(photo), np.full((200, 300), 128, np.uint8))
    spec = {"source": {"plugin": "simulate", "photo": str(photo), "frames": 1200, "height": 64, "width": 96},
            "outputs": {"trajectory_plot": False, "report": False}}
    with pytest.raises(StageError, match=r"level 1: all \d+ pairs .* \(group_size 100 is set in the spec, so the "
                                         r"pairs were not checked .*with group_size: auto they are"):
        photonpano.run({**spec, "group_size": 100}, progress=False)
    with pytest.raises(StageError, match=r"level 1: all \d+ pairs of merged frames failed to register$"):
        photonpano.run(spec, progress=False)  # checked, and still nothing to register: no advice


@pytest.mark.filterwarnings("error::RuntimeWarning")  # the hot-pixel search divided 0 by a deviation of 0
def test_when_no_pair_registers_because_every_pixel_fires_the_error_says_the_capture_is_saturated():
    """1 000 dark counts per pixel per frame: the error gives the detection rate; a bright capture gets no note."""
    import photonpano
    from photonpano.budget import saturation_note
    from photonpano.errors import StageError

    spec = {"source": {"plugin": "simulate", "frames": 1200, "height": 64, "width": 96, "dark_count_rate": 1000.0},
            "outputs": {"trajectory_plot": False, "report": False}}
    with pytest.raises(StageError, match=r"level 1: all \d+ pairs .*failed to register; the capture is saturated: its "
                                         r"pixels detect a photon in 100\.0% of the binary frames"):
        photonpano.run(spec, progress=False)
    assert saturation_note(probe_capture(_capture(flux=3.0))) is None  # flux 3: 34 % of pixel-frames fire
    assert saturation_note(None) is None
