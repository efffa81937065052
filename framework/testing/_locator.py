"""The locator contract (public through :mod:`photonpano.testing`)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest
from numpy.typing import NDArray

from ..stages import MergedFrames
from ._captures import corner_error_px, merged_frames, synthetic_pair
from ._plugin import PluginContract


class LocatorContract(PluginContract):
    """The locator contract (:mod:`photonpano.locator`: ``register_pairs``, ``register_to_template``, the context).

    Class attributes (besides :class:`PluginContract`'s):
        motion: the warps the locator must recover on synthetic frames: ``"translation"``
            (a sub-pixel shift), ``"similarity"`` (shift, rotation, scale) or
            ``"homography"`` (adds perspective).
        tolerance_px: largest accepted mean corner error in pixels, on the pair of
            :attr:`motion` and on the half turn (:meth:`half_turn`). The built-ins reach
            0.02-0.15 px (``opencv-sift``, without sub-pixel polish, 0.40 px on the
            perspective pair); a half-pixel centre error costs 1.4 px on the half turn.
        direct: True for methods that refine ``initial`` (they get a start about 1.5 px
            off the truth); False for methods that ignore it (they get the identity).
        size: ``(height, width)`` of the synthetic frames in pixels.
    """

    motion: ClassVar[str] = "homography"
    tolerance_px: ClassVar[float] = 0.5
    direct: ClassVar[bool] = False
    size: ClassVar[tuple[int, int]] = (160, 240)

    def truth(self) -> NDArray[np.float64]:
        """Return the b-to-a homography of the synthetic pair for :attr:`motion`."""
        h, w = self.size
        cx, cy = (w - 1) / 2, (h - 1) / 2
        move = np.array([[1, 0, 3.3], [0, 1, -2.4], [0, 0, 1]], np.float64)
        if self.motion == "translation":
            return move
        angle, scale = np.deg2rad(2.0), 1.03
        c, s = scale * np.cos(angle), scale * np.sin(angle)
        rot = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy], [0, 0, 1]])
        out = move @ rot
        if self.motion == "homography":
            out = out @ np.array([[1, 0, 0], [0, 1, 0], [1.5e-4, -1e-4, 1]])
        return out / out[2, 2]

    def start(self, truth: NDArray[np.float64]) -> NDArray[np.float64]:
        """Return the ``initial`` estimate given to the locator for the pair with ``truth``."""
        if not self.direct:
            return np.eye(3)
        from photonpano import geometry

        h, w = self.size
        c = geometry.corners(w, h).astype(np.float32)
        off = np.array([[1.2, -0.8], [-1.0, 1.1], [0.9, 1.3], [-1.3, -0.7]], np.float32)
        import cv2

        start = cv2.getPerspectiveTransform(c, (geometry.apply(truth, c) + off).astype(np.float32))
        return start / start[2, 2]

    def _run(self, locator: Any, merged: MergedFrames, pairs: Any, initial: Any):
        from photonpano.stages import Locator, PairRegistrations

        assert isinstance(locator, Locator), f"build() returned {type(locator).__name__}, not a Locator"
        result = locator.register_pairs(merged, np.asarray(pairs, np.int64).reshape(-1, 2),
                                        np.asarray(initial, np.float64).reshape(-1, 3, 3))
        assert isinstance(result, PairRegistrations)
        return result

    def test_returns_documented_shapes_and_dtypes(self, built: Any) -> None:
        """(P, 3, 3) float64 normalised homographies, (P,) int64 counts and bool flags."""
        truth = self.truth()
        merged = synthetic_pair(truth, *self.size)
        inv = np.linalg.inv(truth)
        result = self._run(built, merged, [[0, 1], [1, 0], [0, 1]],
                           [self.start(truth), self.start(inv / inv[2, 2]), self.start(truth)])
        assert result.homographies.shape == (3, 3, 3) and result.homographies.dtype == np.float64
        for name in ("matches", "inliers"):
            arr = getattr(result, name)
            assert arr.shape == (3,) and arr.dtype == np.int64 and (arr >= 0).all(), name
        assert result.ok.shape == (3,) and result.ok.dtype == np.bool_
        ok_h = result.homographies[result.ok]
        assert np.all(np.isfinite(ok_h))
        np.testing.assert_allclose(ok_h[:, 2, 2], 1.0, atol=1e-9)

    def test_recovers_a_known_warp_in_the_right_direction(self, built: Any) -> None:
        """Pair (a, b) gives the map of b's pixels to a's (the pixel-centre convention: :meth:`half_turn`)."""
        truth = self.truth()
        merged = synthetic_pair(truth, *self.size)
        result = self._run(built, merged, [[0, 1]], [self.start(truth)])
        assert result.ok[0], "the synthetic pair failed to register"
        h, w = self.size
        error = corner_error_px(result.homographies[0], truth, w, h)
        inverse_error = corner_error_px(result.homographies[0], np.linalg.inv(truth), w, h)
        assert error <= self.tolerance_px, (
            f"mean corner error {error:.3f} px > {self.tolerance_px} px "
            f"(against the inverse warp: {inverse_error:.3f} px; direction swapped?)")

    def half_turn(self) -> NDArray[np.float64]:
        """Return the b-to-a homography of the pixel-centre case: a half turn, then a shift.

        Frame b is frame a turned by 180 degrees about its centre ``((w - 1) / 2, (h - 1) / 2)``
        (pixel centres at integers) and shifted by (1.3, -0.7) px: ``x -> (w - 1 + 1.3 - x,
        h - 1 - 0.7 - y)``. A locator whose coordinates are off by ``o`` px (e.g. pixel
        centres at half-integers, ``o = (0.5, 0.5)``) reports ``x -> (w - 1 + 1.3 - x + 2 o_x,
        ...)``: a mean corner error of ``2 |o|`` (1.4 px for a half-pixel error). Under a
        pure translation, or the small rotation and zoom of :meth:`truth` (0.03 px), the
        same error hardly shows.
        """
        h, w = self.size
        return np.array([[-1.0, 0.0, w - 1 + 1.3], [0.0, -1.0, h - 1 - 0.7], [0.0, 0.0, 1.0]])

    def test_pixel_centres_at_integers(self, built: Any) -> None:
        """A half turn about the frame centre is recovered within ``tolerance_px`` (see :meth:`half_turn`).

        Skipped for ``motion = "translation"``: a translation is the same in every
        pixel-centre convention.
        """
        if self.motion == "translation":
            pytest.skip("a translation cannot reveal a pixel-centre convention")
        truth = self.half_turn()
        merged = synthetic_pair(truth, *self.size)
        result = self._run(built, merged, [[0, 1]], [self.start(truth)])
        assert result.ok[0], "the half-turned pair failed to register"
        h, w = self.size
        error = corner_error_px(result.homographies[0], truth, w, h)
        assert error <= self.tolerance_px, (
            f"mean corner error {error:.3f} px > {self.tolerance_px} px on a half turn about the frame centre: "
            f"coordinates off by about {error / 2:.2f} px (pixel centres at integers?)")

    def test_reversed_pair_gives_the_inverse(self, built: Any) -> None:
        """Registering (b, a) gives (about) the inverse of registering (a, b)."""
        truth = self.truth()
        inv = np.linalg.inv(truth)
        merged = synthetic_pair(truth, *self.size)
        result = self._run(built, merged, [[0, 1], [1, 0]], [self.start(truth), self.start(inv / inv[2, 2])])
        assert result.ok.all()
        h, w = self.size
        loop = result.homographies[0] @ result.homographies[1]
        assert corner_error_px(loop, np.eye(3), w, h) <= 2 * self.tolerance_px

    def test_pairs_name_frames_by_id(self, built: Any) -> None:
        """Pairs name frames by ``merged.ids``: another order, and a frame no pair names, change nothing.

        The frames come as (b, a frame rolled by a quarter, a) with ids (42, 7, 1000) and
        the pair as ids ``(1000, 42)``: a locator that reads pairs as positions fails here.
        A pair naming an id that is not in the call is refused in one line naming the locator.
        """
        from photonpano.locator import LocatorContext

        truth = self.truth()
        pair = synthetic_pair(truth, *self.size)
        plain = self._run(built, pair, [[0, 1]], [self.start(truth)])
        fields = ("flux", "frames", "images", "masks")
        mixed = MergedFrames(*(np.stack([getattr(pair, f)[1], np.roll(getattr(pair, f)[0], self.size[1] // 4, 1),
                                         getattr(pair, f)[0]]) for f in fields), ids=np.array([42, 7, 1000]))
        once = LocatorContext(reuses_frames=False)  # no cache: the frames are found by id, not remembered
        named = built.register_pairs(mixed, np.array([[1000, 42]]), self.start(truth)[None], once)
        assert named.ok[0] == plain.ok[0], "the pair named by ids registered differently from the same frames"
        np.testing.assert_allclose(named.homographies, plain.homographies, atol=1e-6)
        with pytest.raises(ValueError, match=type(built).__name__) as raised:
            built.register_pairs(mixed, np.array([[1000, 1]]), np.eye(3)[None])
        assert "\n" not in str(raised.value) and "(1000, 1)" in str(raised.value)

    def test_no_pairs_gives_empty_typed_result(self, built: Any) -> None:
        """Zero pairs give zero-length arrays of the documented shapes."""
        merged = synthetic_pair(self.truth(), *self.size)
        result = self._run(built, merged, np.zeros((0, 2), np.int64), np.zeros((0, 3, 3)))
        assert result.homographies.shape == (0, 3, 3) and result.ok.shape == (0,)

    def test_featureless_frame_is_flagged_not_raised(self, built: Any) -> None:
        """A pair with a blank (uniform) frame comes back ``ok=False`` without an exception."""
        pair = synthetic_pair(self.truth(), *self.size)
        blank = np.full(self.size, 0.5, np.float32)
        frames = [pair.flux[0] / np.float32(1e5), blank]
        merged = merged_frames(frames, [pair.masks[0], np.ones(self.size, bool)])
        result = self._run(built, merged, [[0, 1]], [np.eye(3)])
        assert result.homographies.shape == (1, 3, 3)
        assert not result.ok[0], "a blank frame cannot be registered; flag it with ok=False"

    def test_repeatable(self, built: Any) -> None:
        """The same call twice gives the same homographies (caches must not change results)."""
        truth = self.truth()
        merged = synthetic_pair(truth, *self.size)
        first = self._run(built, merged, [[0, 1]], [self.start(truth)])
        second = self._run(built, merged, [[0, 1]], [self.start(truth)])
        np.testing.assert_allclose(first.homographies, second.homographies, atol=1e-6)
        np.testing.assert_array_equal(first.ok, second.ok)

    def _one(self, merged: MergedFrames, index: int) -> MergedFrames:
        """Merged frame ``index`` alone (no content ids)."""
        return MergedFrames(*(getattr(merged, f)[index:index + 1] for f in ("flux", "frames", "images", "masks")))

    def test_registers_a_frame_against_a_template(self, built: Any) -> None:
        """``register_to_template(views, frames)`` maps frame g's pixels to view g's, like the pair (view, frame)."""
        truth = self.truth()
        merged = synthetic_pair(truth, *self.size)
        result = built.register_to_template(self._one(merged, 0), self._one(merged, 1), self.start(truth)[None])
        assert result.homographies.shape == (1, 3, 3) and result.ok[0], "the template registration failed"
        h, w = self.size
        error = corner_error_px(result.homographies[0], truth, w, h)
        assert error <= self.tolerance_px, f"mean corner error {error:.3f} px > {self.tolerance_px} px"

    def test_same_result_on_an_executor_and_without_reuse(self, built: Any, config: Any) -> None:
        """A :class:`~photonpano.locator.LocatorContext` changes how a call runs, never what it finds."""
        from photonpano.executor import make_executor
        from photonpano.locator import LocatorContext

        truth = self.truth()
        inv = np.linalg.inv(truth)
        merged = synthetic_pair(truth, *self.size)
        pairs = np.array([[0, 1], [1, 0]], np.int64)
        initial = np.stack([self.start(truth), self.start(inv / inv[2, 2])])
        serial = config.build().register_pairs(merged, pairs, initial)
        with make_executor("threads", 2) as executor:
            threaded = config.build().register_pairs(merged, pairs, initial, LocatorContext(executor=executor))
        once = config.build().register_pairs(merged, pairs, initial, LocatorContext(reuses_frames=False))
        for other in (threaded, once):
            np.testing.assert_allclose(other.homographies, serial.homographies, atol=1e-6)
            np.testing.assert_array_equal(other.ok, serial.ok)

    def test_bad_arguments_are_refused_in_one_line_naming_the_locator(self, built: Any) -> None:
        """Indices outside the frames, or ``initial`` of the wrong shape, raise a one-line ValueError."""
        merged = synthetic_pair(self.truth(), *self.size)
        name = type(built).__name__
        for pairs, initial in (([[0, 2]], np.eye(3)[None]), ([[0, 1]], np.eye(3)[None].repeat(2, 0))):
            with pytest.raises(ValueError, match=name) as raised:
                built.register_pairs(merged, np.array(pairs, np.int64), initial)
            assert "\n" not in str(raised.value)
