"""The compositor contract (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from ._captures import tiny_capture
from ._plugin import PluginContract


class CompositorContract(PluginContract):
    """The compositor contract (see :class:`photonpano.stages.Compositor`), on :func:`tiny_capture`.

    Class attributes (besides :class:`PluginContract`'s):
        min_psnr_db: the PSNR against the true scene that a panorama composited with the
            true motion must reach (the tiny capture gives about 26-30 dB).
    """

    min_psnr_db: ClassVar[float] = 22.0

    @pytest.fixture(scope="class")
    @classmethod
    def capture(cls) -> Any:
        """The tiny simulated capture (with ground truth)."""
        return tiny_capture()

    def _compose(self, built: Any, capture: Any, **kwargs: Any) -> Any:
        from photonpano.compose import compose

        return compose(capture, capture.ground_truth, built, **kwargs)

    def test_panorama_has_documented_types_and_matches_the_scene(self, built: Any, capture: Any) -> None:
        """(Hc, Wc) float32 flux and frames on the canvas; PSNR vs the scene >= ``min_psnr_db``."""
        from photonpano.metrics import psnr, scene_on_canvas

        pano = self._compose(built, capture)
        shape = pano.flux.shape
        assert pano.flux.dtype == np.float32 and pano.frames.dtype == np.float32
        assert pano.frames.shape == shape and pano.homographies.shape == (capture.n_frames, 3, 3)
        seen = np.isfinite(pano.flux)
        assert seen.mean() > 0.9, f"only {seen.mean():.0%} of the canvas is observed"
        assert np.all(pano.flux[seen] >= 0) and np.all(pano.frames >= 0)
        canvas_from_scene = pano.homographies[0] @ np.linalg.inv(capture.ground_truth[0])
        scene = scene_on_canvas(capture, canvas_from_scene, shape)
        inner = np.zeros(shape, bool)
        inner[4:-4, 4:-4] = True
        value = psnr(pano.flux, scene, inner & seen)
        assert value >= self.min_psnr_db, f"PSNR {value:.1f} dB against the true scene"

    def test_scale_sets_the_canvas(self, config: Any, capture: Any) -> None:
        """A config at ``scale: 2`` paints a canvas about twice as large in each direction."""
        if type(config).missing_requirements():
            pytest.skip("optional requirement missing")
        one = self._compose(config.model_copy(update={"scale": 1.0}).build(), capture)
        two = self._compose(config.model_copy(update={"scale": 2.0}).build(), capture)
        ratio = np.array(two.flux.shape) / np.array(one.flux.shape)
        np.testing.assert_allclose(ratio, 2.0, atol=0.05)

    def test_threads_and_chunks_do_not_change_the_result(self, config: Any, capture: Any) -> None:
        """Fed in small chunks on 3 threads (forks joined) == fed serially in big chunks."""
        if type(config).missing_requirements():
            pytest.skip("optional requirement missing")
        from photonpano.executor import make_executor

        serial = self._compose(config.build(), capture)
        with make_executor("threads", 3) as executor:
            threaded = self._compose(config.build(), capture, chunk_batches=7, executor=executor)
        np.testing.assert_allclose(threaded.frames, serial.frames, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(threaded.flux, serial.flux, rtol=1e-4, atol=1e-2)
