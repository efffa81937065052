"""Intensity frames: response curves, .cih frame rates, mean estimates."""

import numpy as np
import pytest
from photonpano.intensity import estimate_radiance, mean_intensity, read_cih_frame_rate, response_lut
from photonpano.photons import flux_mle, srgb_to_linear


def test_response_luts():
    np.testing.assert_allclose(response_lut("linear", 12), np.arange(4096) / 4095, rtol=1e-6)
    np.testing.assert_allclose(response_lut("srgb", 8), srgb_to_linear(np.arange(256) / 255), rtol=1e-6)
    lut = response_lut("gamma", 8, gamma=2.0, black_level=15, white_level=235)
    assert lut[15] == 0 and lut[235] == 1 and lut[0] == 0 and lut[255] == 1
    assert lut[125] == pytest.approx(((125 - 15) / 220) ** 2, rel=1e-6)
    with pytest.raises(ValueError, match="must exceed black_level"):
        response_lut("linear", 8, black_level=10, white_level=5)


@pytest.mark.parametrize("text, rate", [
    ("#Camera Information Header\nframerate: 1000\n", 1000.0),
    ("Record Rate(fps) : 30000\nShutter Speed(s) : 1/50000\n", 30000.0),
    ("FrameRate = 2500.5\r\n", 2500.5),
    ("Camera: INFINICAM\nnothing else\n", None),
])
def test_cih_frame_rate(tmp_path, text, rate):
    path = tmp_path / "rec.cih"
    path.write_text(text)
    assert read_cih_frame_rate(path) == rate


def test_mean_and_radiance_estimates():
    sums = np.array([[3.0, 0.0], [1.0, 2.0]], np.float32)
    frames = np.array([[4.0, 0.2], [2.0, 4.0]], np.float32)
    mean = mean_intensity(sums, frames)
    np.testing.assert_allclose(mean, [[0.75, np.nan], [0.5, 0.5]])

    class Binary:
        kind, exposure_s = "binary", 1e-5

    class Intensity:
        kind, exposure_s = "intensity", 1e-3

    np.testing.assert_array_equal(estimate_radiance(Intensity(), sums, frames), mean)
    np.testing.assert_array_equal(estimate_radiance(Binary(), sums, frames), flux_mle(sums, frames, 1e-5))
