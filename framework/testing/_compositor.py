"""The compositor contract (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest
from numpy.typing import NDArray

from ._captures import tiny_capture
from ._plugin import PluginContract


def misplacement_px(flux: NDArray[np.float32], capture: Any, compared: NDArray[np.bool_],
                    canvas_from_scene: NDArray[np.float64], iterations: int = 4) -> NDArray[np.float64]:
    """Return the translation that best moves the true scene onto a panorama, in canvas pixels.

    Positive ``dx`` (``dy``): the panorama shows the scene right of (below) where
    ``canvas_from_scene`` puts it.

    Gauss-Newton on ``flux ~ g * scene(T(d) canvas_from_scene)`` over the gain ``g`` and the
    shift ``d = (dx, dy)`` (x right, y down), the scene's derivatives taken by resampling it
    at +-0.25 px. A compositor that paints each frame ``d`` pixels off its homography gives
    about ``d`` (measured: 0.50 and 0.96 px for frames moved by 0.5 and 1 px).

    Args:
        flux: (Hc, Wc) float32 panorama flux (NaN where unobserved).
        capture: the capture with ``scene_flux`` (see :func:`photonpano.metrics.scene_on_canvas`).
        compared: (Hc, Wc) bool pixels to fit.
        canvas_from_scene: (3, 3) float64 map of ground-truth coordinates to canvas pixels.
        iterations: Gauss-Newton steps.

    Returns:
        (2,) float64 ``(dx, dy)`` in canvas pixels.
    """
    from photonpano import geometry
    from photonpano.metrics import scene_on_canvas

    shape, step, d = flux.shape, 0.25, np.zeros(2)
    for _ in range(iterations):
        def at(dx: float, dy: float) -> NDArray[np.float32]:
            return scene_on_canvas(capture, geometry.translation(d[0] + dx, d[1] + dy) @ canvas_from_scene, shape)

        s0 = at(0.0, 0.0)
        jx, jy = (at(step, 0.0) - at(-step, 0.0)) / (2 * step), (at(0.0, step) - at(0.0, -step)) / (2 * step)
        keep = compared & np.isfinite(s0) & np.isfinite(jx) & np.isfinite(jy)
        design = np.stack([flux[keep], -jx[keep], -jy[keep]], 1).astype(np.float64)
        d = d + np.linalg.lstsq(design, s0[keep].astype(np.float64), rcond=None)[0][1:]
    return d


class CompositorContract(PluginContract):
    """The compositor contract (see :class:`photonpano.stages.Compositor`), on :func:`tiny_capture`.

    The panorama of the tiny capture composited with its true motion is compared with the
    true scene resampled onto the canvas (inner pixels, 4 px from the canvas edges):
    its PSNR, its flux calibration and where it puts the scene. The bars are set from
    what the built-in compositors reach (``flux-canvas``, ``drizzle`` with its square,
    point and Gaussian drops: 34.8-35.0 dB, mean flux within 0.2 % of the scene's, offset
    at most 0.07 px) with a margin. A compositor that misplaces every frame by 0.5 px
    fails the PSNR (32.2 dB) and the placement (0.51 px); one that returns mean counts
    per frame instead of flux fails the PSNR (32.8 dB after the gain fit) and the
    calibration (1e-5 x), as does one that divides counts by time without the Poisson
    inversion (32.8 dB, 0.95 x).

    Class attributes (besides :class:`PluginContract`'s):
        min_psnr_db: the PSNR against the true scene (after a least-squares gain fit)
            that the panorama must reach, in dB (built-ins: 34.8-35.0 dB; default 34.0).
        max_gain_error: largest accepted relative error of the flux calibration: the
            panorama's mean flux over the compared pixels divided by the scene's must lie
            within ``1 +- max_gain_error`` (built-ins: within 0.002; default 0.02).
        max_offset_px: largest accepted misplacement of the scene on the canvas, in
            canvas pixels: the length of the translation that best aligns the scene with
            the panorama (:func:`misplacement_px`; built-ins: at most 0.07 px; default 0.2).
    """

    min_psnr_db: ClassVar[float] = 34.0
    max_gain_error: ClassVar[float] = 0.02
    max_offset_px: ClassVar[float] = 0.2

    @pytest.fixture(scope="class")
    @classmethod
    def capture(cls) -> Any:
        """The tiny simulated capture (with ground truth)."""
        return tiny_capture()

    @pytest.fixture(scope="class")
    @classmethod
    def panorama(cls, built: Any, capture: Any) -> Any:
        """The panorama of :func:`capture` composited with its true motion (one per test class)."""
        return cls()._compose(built, capture)

    def _compose(self, built: Any, capture: Any, **kwargs: Any) -> Any:
        from photonpano.compose import compose

        return compose(capture, capture.ground_truth, built, **kwargs)

    @staticmethod
    def _scene(panorama: Any, capture: Any) -> tuple[Any, Any, Any]:
        """``(scene, compared, canvas_from_scene)``: the true flux on the canvas and the pixels compared."""
        from photonpano.metrics import scene_on_canvas

        shape = panorama.flux.shape
        canvas_from_scene = panorama.homographies[0] @ np.linalg.inv(capture.ground_truth[0])
        scene = scene_on_canvas(capture, canvas_from_scene, shape)
        inner = np.zeros(shape, bool)
        inner[4:-4, 4:-4] = True
        return scene, inner & np.isfinite(panorama.flux) & np.isfinite(scene), canvas_from_scene

    def test_panorama_has_documented_types_and_matches_the_scene(self, panorama: Any, capture: Any) -> None:
        """(Hc, Wc) float32 flux and frames on the canvas; PSNR vs the scene >= ``min_psnr_db``."""
        from photonpano.metrics import psnr

        pano = panorama
        shape = pano.flux.shape
        assert pano.flux.dtype == np.float32 and pano.frames.dtype == np.float32
        assert pano.frames.shape == shape and pano.homographies.shape == (capture.n_frames, 3, 3)
        seen = np.isfinite(pano.flux)
        assert seen.mean() > 0.9, f"only {seen.mean():.0%} of the canvas is observed"
        assert np.all(pano.flux[seen] >= 0) and np.all(pano.frames >= 0)
        scene, compared, _ = self._scene(pano, capture)
        value = psnr(pano.flux, scene, compared)
        assert value >= self.min_psnr_db, f"PSNR {value:.2f} dB against the true scene < {self.min_psnr_db} dB"

    def test_flux_is_calibrated_in_photons_per_second(self, panorama: Any, capture: Any) -> None:
        """The panorama's mean flux is the scene's (photons/s) within ``max_gain_error``."""
        scene, compared, _ = self._scene(panorama, capture)
        ratio = float(np.sum(panorama.flux[compared], dtype=np.float64) / np.sum(scene[compared], dtype=np.float64))
        assert abs(ratio - 1.0) <= self.max_gain_error, (
            f"the panorama's mean flux is {ratio:.4g} x the scene's: flux must be the photon flux "
            f"(photons/s, the MLE of paper Eq. 3), not counts or a detection rate")

    def test_frames_land_where_their_homographies_say(self, panorama: Any, capture: Any) -> None:
        """The scene sits on the canvas within ``max_offset_px`` of where the homographies put it."""
        offset = misplacement_px(panorama.flux, capture, *self._scene(panorama, capture)[1:])
        assert np.hypot(*offset) <= self.max_offset_px, (
            f"the panorama is offset by ({offset[0]:+.3f}, {offset[1]:+.3f}) canvas px from the true scene "
            f"(> {self.max_offset_px} px): pixel centres at integers, frame-to-canvas homographies as given?")

    def test_scale_sets_the_canvas(self, config: Any, capture: Any) -> None:
        """A config at ``scale: 2`` paints a canvas about twice as large, the scene where its homographies say.

        Placement as in :meth:`test_frames_land_where_their_homographies_say`, within
        ``max_offset_px`` canvas pixels (built-ins at scale 2: at most 0.075 px).
        """
        if type(config).missing_requirements():
            pytest.skip("optional requirement missing")
        one = self._compose(config.model_copy(update={"scale": 1.0}).build(), capture)
        two = self._compose(config.model_copy(update={"scale": 2.0}).build(), capture)
        ratio = np.array(two.flux.shape) / np.array(one.flux.shape)
        np.testing.assert_allclose(ratio, 2.0, atol=0.05)
        offset = misplacement_px(two.flux, capture, *self._scene(two, capture)[1:])
        assert np.hypot(*offset) <= self.max_offset_px, (
            f"at scale 2 the panorama is offset by ({offset[0]:+.3f}, {offset[1]:+.3f}) canvas px from the true "
            f"scene (> {self.max_offset_px} px)")

    def test_threads_and_chunks_do_not_change_the_result(self, config: Any, capture: Any) -> None:
        """Fed in small chunks on 3 threads (forks joined) == fed serially in big chunks.

        The accumulated frames must agree to float32 rounding (rtol 1e-4). The flux to
        rtol 5e-3: a compositor may restore its canvas with a thresholding estimator
        (drizzle's Wiener restoration zeroes DCT coefficients under 2.7 noise standard
        deviations), where a coefficient at its threshold flips with the summation order
        (drizzle with Gaussian drops: 64 of 7 194 canvas pixels, at most 0.18 %). A lost or
        doubled chunk shows in the frames.
        """
        if type(config).missing_requirements():
            pytest.skip("optional requirement missing")
        from photonpano.executor import make_executor

        serial = self._compose(config.build(), capture)
        with make_executor("threads", 3) as executor:
            threaded = self._compose(config.build(), capture, chunk_batches=7, executor=executor)
        np.testing.assert_allclose(threaded.frames, serial.frames, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(threaded.flux, serial.flux, rtol=5e-3, atol=1e-2)
