"""The pictures of a run: trajectory.png on a static clip, panorama.png's transparency."""

from types import SimpleNamespace

import cv2
import numpy as np
from photonpano.metrics import TRAJECTORY_MIN_SPAN_PX, plot_trajectory, trajectory_figure
from photonpano.photons import tone_map
from photonpano.png import write_panorama_png


def _translations(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h = np.repeat(np.eye(3)[None], len(x), axis=0)
    h[:, 0, 2], h[:, 1, 2] = x, y
    return h


def _source(frames: int):
    return SimpleNamespace(width=64, height=48, frame_rate_hz=1000.0, ground_truth=None, n_frames=frames)


def _drawn(fig):
    fig.canvas.draw()
    return fig.axes


def test_a_static_clip_is_drawn_over_a_pixel_without_offset():
    rng = np.random.default_rng(0)
    # a static camera: sub-pixel jitter (0.08 px span) around a centre far from 0
    h = _translations(1000.0 + rng.uniform(-0.04, 0.04, 200), 700.0 + rng.uniform(-0.04, 0.04, 200))
    fig = trajectory_figure(h, h, _source(200), None)
    try:
        for ax, centre in zip(_drawn(fig)[:2], (1000.0 + 31.5, 700.0 + 23.5)):
            low, high = ax.get_ylim()
            assert high - low >= TRAJECTORY_MIN_SPAN_PX - 1e-9
            assert low < centre < high
            assert ax.yaxis.get_offset_text().get_text() == ""  # no "+1.031e3" label
            labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
            assert labels and all(float(text.replace("\u2212", "-")) > 500 for text in labels)
    finally:
        import matplotlib.pyplot as plt
        plt.close(fig)


def test_a_moving_clip_keeps_its_own_range():
    t = np.arange(200.0)
    h = _translations(2.0 * t, 0.5 * t)
    fig = trajectory_figure(h, h, _source(200), None, np.full(200, 0.1))
    try:
        axes = _drawn(fig)
        assert len(axes) == 3
        low, high = axes[0].get_ylim()
        assert 398 < high - low < 460  # autoscaled to the 398 px of motion (plus margins)
    finally:
        import matplotlib.pyplot as plt
        plt.close(fig)


def test_plot_trajectory_writes_the_png(tmp_path):
    h = _translations(np.full(10, 5.0), np.full(10, 5.0))
    plot_trajectory(tmp_path / "trajectory.png", h, h, _source(10), None)
    image = cv2.imread(str(tmp_path / "trajectory.png"))
    assert image is not None and image.shape[1] == 800


def test_panorama_png_is_transparent_where_unobserved(tmp_path):
    rng = np.random.default_rng(1)
    flux = rng.uniform(0, 100, (37, 53)).astype(np.float32)
    flux[:5] = np.nan
    flux[10:20, 40:] = np.nan
    write_panorama_png(tmp_path / "panorama.png", flux)
    png = cv2.imread(str(tmp_path / "panorama.png"), cv2.IMREAD_UNCHANGED)  # grey in B, G, R; alpha
    assert png.dtype == np.uint16 and png.shape == (37, 53, 4)
    expected = tone_map(flux, bits=16)
    for channel in range(3):
        np.testing.assert_array_equal(png[..., channel], expected)
    np.testing.assert_array_equal(png[..., 3], np.where(np.isfinite(flux), 65535, 0))
