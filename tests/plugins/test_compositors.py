"""Compositors: photonpano.testing's contract on every built-in, and drizzle's resolution."""

import cv2
import numpy as np
import pytest
from photonpano.compose import BilinearCompositor, compose
from photonpano.plugins.compositors.drizzle import Drizzle, DrizzleConfig
from photonpano.plugins.compositors.flux_canvas import FluxCanvasConfig
from photonpano.plugins.sources.simulate import SimulateConfig
from photonpano.testing import CompositorContract


class TestFluxCanvas(CompositorContract):
    """The bilinear compositor keeps the contract."""

    config_class = FluxCanvasConfig
    entry_point = "flux-canvas"


class TestDrizzle(CompositorContract):
    """Drizzle with its default square drop keeps the contract."""

    config_class = DrizzleConfig
    entry_point = "drizzle"


class TestDrizzlePointKernel(CompositorContract):
    """Drizzle with point drops keeps the contract."""

    config_class = DrizzleConfig
    config_kwargs = {"kernel": "point"}


class TestDrizzleGaussianKernel(CompositorContract):
    """Drizzle with Gaussian drops keeps the contract."""

    config_class = DrizzleConfig
    config_kwargs = {"kernel": "gaussian", "pixfrac": 0.8}


PERIOD = 3.0
"""Scene pixels per cycle of the test pattern: 1.5 frame pixels at pixel pitch 2, finer
than the sensor's Nyquist limit (2 frame pixels per cycle)."""


@pytest.fixture(scope="module")
def bars(tmp_path_factory):
    """An undersampled capture (pixel pitch 2) of vertical sinusoidal bars, 3 scene px per cycle."""
    from photonpano.photons import linear_to_srgb

    x = np.arange(480)
    linear = 0.5 + 0.4 * np.sin(2 * np.pi * x / PERIOD)
    image = np.repeat(linear[None, :], 240, axis=0)
    path = tmp_path_factory.mktemp("bars") / "bars.png"
    srgb = np.rint(linear_to_srgb(image) * 65535).astype(np.uint16)
    cv2.imwrite(str(path), np.repeat(srgb[..., None], 3, axis=2))
    return SimulateConfig(photo=path, scene_width=480, frames=3000, height=48, width=64, pixel_pitch=2,
                          flux=4.0, speed_px_per_frame=0.02, vibration_px=3.0, vibration_hz=200.0).build()


def _modulation(pano, source) -> float:
    """Amplitude / mean of the bar pattern in the panorama's central rows, in scene coordinates."""
    canvas_from_scene = pano.homographies[0] @ np.linalg.inv(source.ground_truth[0])
    from photonpano import geometry

    scene_from_canvas = geometry.scale_matrix(source.scene_pitch) @ np.linalg.inv(canvas_from_scene)
    h, w = pano.flux.shape
    ys, xs = np.mgrid[6:h - 6, 6:w - 6]
    points = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    scene_x = geometry.apply(scene_from_canvas[None], points)[0][:, 0]
    values = pano.flux[6:h - 6, 6:w - 6].ravel().astype(np.float64)
    keep = np.isfinite(values)
    phase = 2 * np.pi * scene_x[keep] / PERIOD
    design = np.stack([np.ones(keep.sum()), np.sin(phase), np.cos(phase)], axis=1)
    coef, *_ = np.linalg.lstsq(design, values[keep], rcond=None)
    return float(np.hypot(coef[1], coef[2]) / coef[0])


def test_drizzle_at_scale_2_resolves_bars_finer_than_the_frame_pixels(bars):
    """Bars of 1.5 frame pixels per cycle: drizzle at scale 2 keeps them, bilinear merges cannot.

    The pattern's true modulation is 0.8 (in linear flux, before the photon MLE's
    compression); the frames undersample it, so no frame-pixel canvas can hold it.
    """
    truth = bars.ground_truth
    drizzle = compose(bars, truth, Drizzle(scale=2.0, kernel="square", pixfrac=0.5))
    point = compose(bars, truth, Drizzle(scale=2.0, kernel="point"))
    bilinear = compose(bars, truth, BilinearCompositor(scale=2.0))
    adaptive = compose(bars, truth, DrizzleConfig(scale=2.0).build())  # the default: noise-adaptive
    scale_1 = compose(bars, truth, DrizzleConfig(scale=1.0).build())
    m_drizzle, m_point, m_bilinear, m_adaptive, m_scale_1 = (
        _modulation(p, bars) for p in (drizzle, point, bilinear, adaptive, scale_1))
    print(f"modulation: drizzle {m_drizzle:.3f}, point {m_point:.3f}, bilinear {m_bilinear:.3f}, "
          f"noise-adaptive {m_adaptive:.3f}, scale 1 {m_scale_1:.3f}")
    assert m_drizzle > 0.35, m_drizzle
    assert m_point > m_drizzle
    assert m_adaptive > 0.9 * m_drizzle, (m_adaptive, m_drizzle)  # the blend keeps resolved detail
    assert m_bilinear < 0.5 * m_drizzle, (m_bilinear, m_drizzle)
    # a frame-pixel canvas cannot hold the bars (the default's restoration at scale 1 keeps
    # their alias, 0.24, as the area-averaged reference on that canvas has it)
    assert m_scale_1 < 0.4 * m_adaptive, (m_scale_1, m_adaptive)


def test_noise_adaptive_blend_smooths_photon_noise_and_keeps_detail():
    """A flat field's binomial noise is cut by more than 4x; bars above the noise are kept."""
    from photonpano.plugins.compositors._adaptive import blend_sums, drop_sharpness

    rng = np.random.default_rng(5)
    frames = np.full((120, 160), 400.0, np.float32)
    flat = rng.binomial(400, 0.3, frames.shape).astype(np.float32)
    out = blend_sums(flat, frames, 2.0, 2.0, drop_sharpness("point", 1.0)) / frames
    inner = np.s_[10:-10, 10:-10]
    assert abs(out[inner].mean() - 0.3) < 0.003
    assert out[inner].std() < 0.25 * (flat / frames)[inner].std(), (out[inner].std(), (flat / frames)[inner].std())
    p = 0.3 + 0.2 * np.sin(np.pi * np.arange(160) / 2)[None, :].repeat(120, axis=0)  # 4 canvas px per cycle
    frames[:] = 40_000
    bars = rng.binomial(40_000, p).astype(np.float32)
    kept = blend_sums(bars, frames, 2.0, 2.0, drop_sharpness("point", 1.0)) / frames
    assert np.abs(kept - p)[inner].max() < 0.03, np.abs(kept - p)[inner].max()


def test_drop_sharpness_matches_simulated_drops():
    """sum(w^2) / sum(w) of square drops at random phases agrees with the closed form."""
    from photonpano.plugins.compositors._adaptive import drop_sharpness

    rng = np.random.default_rng(6)
    for side in (0.5, 1.0, 2.0):
        start = rng.uniform(0, 1, 20_000)
        cells = np.arange(-1, 4)[None, :]
        overlap = np.clip(np.minimum(start[:, None] + side, cells + 1) - np.maximum(start[:, None], cells), 0, None)
        axis = np.mean(np.sum((overlap / side) ** 2, axis=1))
        assert abs(drop_sharpness("square", side) - axis ** 2) < 0.01, side
    assert drop_sharpness("point", 1.0) == 1.0


def _square_drops_reference(counts, n_frames, homographies, weights, shape, pixfrac):
    """Square drops by brute force: each frame pixel's overlap area with every canvas pixel."""
    from photonpano import geometry

    acc = np.zeros((*shape, 2))
    h, w = counts.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w]
    centres = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    rows, cols = np.arange(shape[0]), np.arange(shape[1])
    for b, m in enumerate(homographies):
        side = pixfrac * np.sqrt(abs(np.linalg.det(m[:2, :2]))) / abs(m[2, 2])
        u, v = geometry.apply(m[None], centres)[0].T
        half = side / 2
        ox = np.clip(np.minimum(u[:, None] + half, cols + 0.5) - np.maximum(u[:, None] - half, cols - 0.5), 0, None)
        oy = np.clip(np.minimum(v[:, None] + half, rows + 0.5) - np.maximum(v[:, None] - half, rows - 0.5), 0, None)
        wt = weights.ravel()
        acc[..., 0] += np.einsum("pi,pj->ij", oy, ox * (counts[b].ravel() * wt)[:, None]) / side ** 2
        acc[..., 1] += np.einsum("pi,pj->ij", oy, ox * (n_frames[b] * wt)[:, None]) / side ** 2
    return acc


@pytest.mark.parametrize("scale, pixfrac", [(1.0, 1.0), (2.0, 0.5), (2.0, 0.3), (1.0, 1.7)])
def test_square_drops_match_their_overlap_areas(scale, pixfrac):
    """Square drops spread each count by the drop's overlap area with the canvas pixels.

    Covers the fast path (rows inside the canvas), the edge path and large drops.
    """
    from photonpano import geometry
    from photonpano.plugins.compositors._splat import splat_square

    rng = np.random.default_rng(3)
    counts = rng.integers(0, 40, (3, 9, 12)).astype(np.uint16)
    n_frames = np.array([7, 9, 11])
    weights = rng.uniform(0, 1, (9, 12)).astype(np.float32)
    weights[2, 3] = 0
    shape = (int(14 * scale), int(17 * scale))
    homographies = np.stack([geometry.scale_matrix(scale) @ np.array(m) for m in (
        [[1, 0, 1.3], [0, 1, 2.6], [0, 0, 1]],                      # inside the canvas
        [[0.998, -0.03, -1.2], [0.03, 0.998, 3.1], [1e-4, 0, 1]],   # leaves it on the left
        [[1, 0.01, 4.45], [0, 1, -0.7], [0, 0, 1]])])               # and at the top
    acc = np.zeros((*shape, 2), np.float32)
    splat_square(counts, n_frames, homographies, weights, acc, pixfrac)
    expected = _square_drops_reference(counts, n_frames, homographies, weights, shape, pixfrac)
    np.testing.assert_allclose(acc, expected, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("kernel", ["square", "point"])
def test_frames_at_or_past_the_canvas_edge_never_write_outside_it(kernel):
    """Frames at the canvas edge, past the line at infinity or NaN never write outside the canvas.

    Rows ending a hair inside the last canvas row, a denominator crossing zero along a
    row and NaN homographies: a guard array after the canvas stays untouched, and the
    splat matches the bounds-checked reference where it is defined.
    """
    from photonpano.plugins.compositors._splat import splat_point, splat_square

    counts = np.full((3, 6, 8), 5, np.uint16)
    n_frames, weights, shape = np.array([3, 3, 3]), np.ones((6, 8), np.float32), (10, 12)
    edge = shape[0] - 1 - 5 - 1e-9  # the last frame row lands 1e-9 px inside row 9 (float32: on it)
    homographies = np.array([
        [[1, 0, 2.0], [0, 1, edge], [0, 0, 1]],
        [[1, 0, 11.0 - 7 - 1e-9], [0, 1, 1.0], [0, 0, 1]],
        [[1, 0, 1.0], [0, 1, 1.0], [-0.2, 0, 1]]], float)  # the line at infinity at column 5
    storage = np.zeros(2 * shape[0] * shape[1] + 64, np.float32)
    acc = storage[:2 * shape[0] * shape[1]].reshape(*shape, 2)
    if kernel == "square":
        splat_square(counts, n_frames, homographies, weights, acc, 1.0)
        expected = _square_drops_reference(counts[:2], n_frames[:2], homographies[:2], weights, shape, 1.0)
        first = np.zeros((*shape, 2), np.float32)
        splat_square(counts[:2], n_frames[:2], homographies[:2], weights, first, 1.0)
        np.testing.assert_allclose(first, expected, rtol=1e-4, atol=1e-3)
    else:
        splat_point(counts, n_frames, homographies, weights, acc)
    assert not storage[2 * shape[0] * shape[1]:].any()
    assert np.isfinite(acc).all()


def test_drizzle_skips_frames_without_finite_homographies():
    """The compiled kernels assume finite numbers: a NaN homography's frames are left out, not splatted."""
    from photonpano.records import Canvas

    drizzle = Drizzle(1.0, "square", 1.0)
    drizzle.prepare(Canvas(10, 12, np.eye(3)[None]), None)
    h = np.array([[[1, 0, 2.0], [0, 1, 2.0], [0, 0, 1]], [[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]])
    drizzle.feed(np.full((2, 6, 8), 5, np.uint16), np.array([3, 3]), h)
    assert drizzle._acc[..., 1].sum() == pytest.approx(6 * 8 * 3)


def test_drops_just_over_a_canvas_pixel_are_one_canvas_pixel():
    """Drops within SIDE_TOLERANCE of a canvas pixel are one canvas pixel: within the excess of the exact drop."""
    from photonpano.plugins.compositors._splat import SIDE_TOLERANCE, splat_square

    rng = np.random.default_rng(5)
    counts = rng.integers(0, 40, (2, 9, 12)).astype(np.uint16)
    n_frames, weights, shape = np.array([7, 9]), np.ones((9, 12), np.float32), (14, 17)
    homographies = np.array([[[1, 0, 1.3], [0, 1, 2.6], [0, 0, 1]], [[1, 0, 3.45], [0, 1, 0.7], [0, 0, 1]]], float)
    excess = SIDE_TOLERANCE / 2
    out = {}
    for pixfrac in (1.0, 1.0 + excess):
        out[pixfrac] = np.zeros((*shape, 2), np.float32)
        splat_square(counts, n_frames, homographies, weights, out[pixfrac], pixfrac)
    np.testing.assert_array_equal(out[1.0], out[1.0 + excess])
    exact = _square_drops_reference(counts, n_frames, homographies, weights, shape, 1.0 + excess)
    # each weight moves by at most the excess, and a canvas pixel takes at most 4 drops per image
    assert np.abs(out[1.0][..., 0] - exact[..., 0]).max() <= 4 * excess * 2 * counts.max()


def test_point_drops_land_in_the_pixel_of_their_centre():
    """Point drops add each count to the canvas pixel whose square holds the centre."""
    from photonpano import geometry
    from photonpano.plugins.compositors._splat import splat_point

    rng = np.random.default_rng(4)
    counts = rng.integers(0, 40, (2, 9, 12)).astype(np.uint16)
    weights = np.ones((9, 12), np.float32)
    homographies = np.stack([geometry.scale_matrix(2.0) @ np.array(m) for m in (
        [[1, 0, 1.3], [0, 1, 2.6], [0, 0, 1]], [[0.998, -0.03, -1.2], [0.03, 0.998, 3.1], [1e-4, 0, 1]])])
    shape = (28, 34)
    acc = np.zeros((*shape, 2), np.float32)
    splat_point(counts, np.array([5, 6]), homographies, weights, acc)
    expected = np.zeros(shape)
    ys, xs = np.mgrid[0:9, 0:12]
    centres = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    for b, m in enumerate(homographies):
        u, v = geometry.apply(m[None], centres)[0].T
        j, i = np.floor(u + 0.5).astype(int), np.floor(v + 0.5).astype(int)
        keep = (i >= 0) & (i < shape[0]) & (j >= 0) & (j < shape[1])
        np.add.at(expected, (i[keep], j[keep]), counts[b].ravel()[keep])
    np.testing.assert_allclose(acc[..., 0], expected, rtol=1e-6)


@pytest.mark.parametrize("scale", [1.0, 2.0, 3.0])
def test_canvas_follows_the_super_resolution_convention(scale):
    """docs/conventions.md: canvas pixel = s * (x + 0.5) - 0.5 from the footprint's outer edge."""
    from photonpano.compose import canvas_homographies
    from photonpano.geometry import apply

    to_canvas, (ch, cw) = canvas_homographies(np.eye(3)[None], 8, 4, scale)
    np.testing.assert_allclose(apply(to_canvas[0], np.array([[0.0, 0.0], [7.0, 3.0]])),
                               [[scale * 0.5 - 0.5] * 2, [scale * 7.5 - 0.5, scale * 3.5 - 0.5]], atol=1e-12)
    assert (ch, cw) == (int(4 * scale), int(8 * scale))
