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
    m_drizzle, m_point, m_bilinear = (_modulation(p, bars) for p in (drizzle, point, bilinear))
    print(f"modulation: drizzle {m_drizzle:.3f}, point {m_point:.3f}, bilinear {m_bilinear:.3f}")
    assert m_drizzle > 0.35, m_drizzle
    assert m_point > m_drizzle
    assert m_bilinear < 0.5 * m_drizzle, (m_bilinear, m_drizzle)
