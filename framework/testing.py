"""Contract tests for photonpano plugins: subclass one class per plugin in your test suite.

Every plugin kind has a contract class whose ``test_*`` methods pytest collects when you
subclass it in a test module (name the subclass ``Test...``). Set the class attributes
and, for stages that need data, override the documented methods::

    # tests/test_contract.py of a third-party locator package
    from photonpano.testing import LocatorContract
    from photonpano_phasecorr.plugin import PhaseCorrConfig

    class TestPhaseCorr(LocatorContract):
        config_class = PhaseCorrConfig
        entry_point = "phasecorr"        # checks discovery through the entry point
        motion = "translation"           # the synthetic warps it must recover

The checks: the config class is a valid, documented, frozen, strict, picklable and
schema-exportable model of its stage; the plugin is found through its entry point and
selectable in a spec; registering it imports no heavy module; and the built object keeps
the stage's contract on tiny synthetic data (shapes, dtypes, coordinate conventions and
directions, failures flagged rather than raised, repeatable results). See
``docs/writing_plugins.md``.

This module imports pytest, numpy and pydantic only; OpenCV is imported by the tests
that make synthetic frames. Contract classes:

- :class:`PluginContract`: config-level checks shared by every kind;
- :class:`SourceContract`, :class:`ResamplerContract`, :class:`MergerContract`,
  :class:`LocatorContract`, :class:`InterpolatorContract`, :class:`CompositorContract`,
  :class:`PoseEstimatorContract`:
  the stage's behaviour.

Helpers for your own tests: :func:`textured_image`, :func:`synthetic_pair`,
:func:`merged_frames`, :func:`corner_error_px`, :func:`tiny_capture`.
"""

from __future__ import annotations

import json
import pickle
import re
import subprocess
import sys
from typing import Any, ClassVar

import numpy as np
import pytest
from numpy.typing import NDArray

from .stages import STAGES, MergedFrames, StageConfig

__all__ = [
    "PluginContract",
    "SourceContract",
    "ResamplerContract",
    "MergerContract",
    "LocatorContract",
    "InterpolatorContract",
    "CompositorContract",
    "PoseEstimatorContract",
    "textured_image",
    "synthetic_pair",
    "merged_frames",
    "corner_error_px",
    "tiny_capture",
    "HEAVY_MODULES",
]

HEAVY_MODULES = ("cv2", "torch", "kornia", "pycolmap", "numba")
"""Modules that registering a plugin (importing its entry-point module) must not import."""


# --- synthetic data ---------------------------------------------------------------------


def textured_image(height: int = 160, width: int = 240, seed: int = 0) -> NDArray[np.float32]:
    """Return a crop of the bundled real photograph as linear intensity.

    Args:
        height: rows in pixels.
        width: columns in pixels.
        seed: picks the crop position (repeatable): the most detailed of 40 candidates.

    Returns:
        (height, width) float32 linear intensity in [0, 1] (the photo's sRGB values
        raised to 2.2).

    Raises:
        ValueError: if the crop is larger than the (720, 1440) resized photo.
    """
    import cv2
    from photonpano.plugins.sources.simulate import bundled_photo

    photo = cv2.imread(str(bundled_photo()), cv2.IMREAD_GRAYSCALE)
    photo = cv2.resize(photo, (1440, 720), interpolation=cv2.INTER_AREA)
    if height > 720 or width > 1440:
        raise ValueError(f"textured_image: {height}x{width} is larger than the 720x1440 photo")
    # the most detailed of 40 seeded candidate crops (density of FAST corners)
    corners = cv2.FastFeatureDetector_create(threshold=25).detect(photo)
    detail = np.zeros(photo.shape, np.float32)
    for k in corners:
        detail[int(k.pt[1]), int(k.pt[0])] = 1.0
    rng = np.random.default_rng(seed)
    ys = rng.integers(0, 720 - height + 1, 40)
    xs = rng.integers(0, 1440 - width + 1, 40)
    best = int(np.argmax([detail[y:y + height, x:x + width].mean() for y, x in zip(ys, xs)]))
    y, x = int(ys[best]), int(xs[best])
    return (photo[y:y + height, x:x + width].astype(np.float32) / 255.0) ** 2.2


def merged_frames(images: list[NDArray[np.float32]],
                  masks: list[NDArray[np.bool_]] | None = None) -> MergedFrames:
    """Pack linear images into a :class:`~photonpano.stages.MergedFrames` as a merger would.

    Args:
        images: G (H, W) float32 linear intensities in [0, 1]; NaN marks unobserved pixels.
        masks: G (H, W) bool trusted pixels (default: the finite pixels).

    Returns:
        Merged frames: ``flux`` = images in photons/s (scaled by 1e5), ``images`` their
        sRGB-like uint8 tone map (0 where unobserved), ``frames`` = 500 where observed.
    """
    flux = np.stack(images).astype(np.float32) * np.float32(1e5)
    finite = np.isfinite(flux)
    mask = np.stack(masks).astype(bool) & finite if masks is not None else finite
    white = float(np.nanpercentile(flux, 99.5)) or 1.0
    tone = np.clip(np.nan_to_num(flux, nan=0.0) / white, 0, 1) ** (1 / 2.2)
    return MergedFrames(flux=flux, frames=np.where(finite, 500.0, 0.0).astype(np.float32),
                        images=np.round(tone * 255).astype(np.uint8), masks=mask)


def synthetic_pair(homography: NDArray[np.float64], height: int = 160, width: int = 240, *,
                   noise: float = 0.01, border_px: int = 4, seed: int = 0) -> MergedFrames:
    """Return two merged frames related by a known homography.

    Frame 0 (``a``) is a crop of the bundled photo; frame 1 (``b``) shows the same scene
    so that ``homography`` maps b's pixel coordinates to a's (photonpano's convention: x
    right, y down, pixel centres at integers): ``b(x) = a(H x)``. A ``border_px`` strip
    of each frame is marked unobserved (NaN flux, mask False), as in real merged frames.

    Args:
        homography: (3, 3) float64 b-to-a homography.
        height: frame height in pixels.
        width: frame width in pixels.
        noise: standard deviation of added Gaussian noise (relative to white).
        border_px: width of the unobserved strip at each frame edge.
        seed: noise and crop seed.

    Returns:
        Two merged frames (see :func:`merged_frames`).
    """
    import cv2

    margin = 40
    big = textured_image(height + 2 * margin, width + 2 * margin, seed)
    shift = np.array([[1, 0, margin], [0, 1, margin], [0, 0, 1]], np.float64)
    a = big[margin:margin + height, margin:margin + width]
    # b(x) = big(shift @ H @ x)
    b = cv2.warpPerspective(big, shift @ homography, (width, height),
                            flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    rng = np.random.default_rng(seed)
    frames, masks = [], []
    for image in (a, b):
        image = np.clip(image + rng.normal(0, noise, image.shape), 0, 1).astype(np.float32)
        mask = np.zeros(image.shape, bool)
        mask[border_px:height - border_px, border_px:width - border_px] = True
        frames.append(np.where(mask, image, np.nan).astype(np.float32))
        masks.append(mask)
    return merged_frames(frames, masks)


def corner_error_px(estimated: NDArray[np.float64], truth: NDArray[np.float64], width: int,
                    height: int) -> float:
    """Return the mean distance (pixels) between the frame corners mapped by two homographies."""
    from photonpano import geometry

    c = geometry.corners(width, height)
    return float(np.linalg.norm(geometry.apply(estimated, c) - geometry.apply(truth, c), axis=-1).mean())


def tiny_capture(frames: int = 1200, height: int = 64, width: int = 96, seed: int = 0) -> Any:
    """Return a small simulated capture with ground truth (the built-in ``simulate`` source).

    Args:
        frames: binary frames T.
        height: frame height in pixels.
        width: frame width in pixels (a multiple of 8).
        seed: photon seed.
    """
    from photonpano.plugins.sources.simulate import SimulateConfig

    return SimulateConfig(frames=frames, height=height, width=width, flux=0.5, vibration_px=1.0,
                          speed_px_per_frame=0.01, seed=seed).build()


# --- config-level contract ----------------------------------------------------------------


class PluginContract:
    """Checks every plugin config class must pass, whatever its stage kind.

    Class attributes (set them in your subclass):
        config_class: the plugin's config class (required).
        config_kwargs: field values for a valid instance (default: none; sources
            usually need some). Override :meth:`make_config` for values computed at test
            time (a temporary file, say).
        entry_point: the entry-point name in the ``photonpano.plugins`` group, to check
            discovery; None skips those checks (plugins registered in code).
        heavy_modules: modules that importing the plugin's entry-point module must not
            import (default :data:`HEAVY_MODULES`).
    """

    config_class: ClassVar[type[StageConfig]]
    config_kwargs: ClassVar[dict[str, Any]] = {}
    entry_point: ClassVar[str | None] = None
    heavy_modules: ClassVar[tuple[str, ...]] = HEAVY_MODULES

    # hooks -----------------------------------------------------------------------------

    def make_config(self, tmp_path_factory: pytest.TempPathFactory) -> StageConfig:
        """Return a valid config instance (default: ``config_class(**config_kwargs)``)."""
        return self.config_class(**self.config_kwargs)

    @pytest.fixture(scope="class")
    @classmethod
    def config(cls, tmp_path_factory: pytest.TempPathFactory) -> StageConfig:
        """A valid config instance of the plugin (one per test class)."""
        return cls().make_config(tmp_path_factory)

    @pytest.fixture(scope="class")
    @classmethod
    def built(cls, config: StageConfig) -> Any:
        """The built stage object (skipped with the install hint if an extra is missing)."""
        missing = type(config).missing_requirements()
        if missing:
            pytest.skip(f"needs {', '.join(missing)}: {type(config).install_hint}")
        return config.build()

    @property
    def key(self) -> str:
        """The plugin key (``plugin`` field default)."""
        return self.config_class.model_fields["plugin"].default

    # checks ------------------------------------------------------------------------------

    def test_config_class_is_a_stage_config(self) -> None:
        """Subclasses one stage's config base and pins a kebab-case ``plugin`` key."""
        assert issubclass(self.config_class, StageConfig)
        assert self.config_class.stage in STAGES, f"unknown stage kind {self.config_class.stage!r}"
        assert issubclass(self.config_class, STAGES[self.config_class.stage])
        assert isinstance(self.key, str) and re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", self.key), \
            f"plugin key {self.key!r} should be kebab-case"

    def test_every_field_is_documented(self) -> None:
        """Each field has a description (a docstring on the line below it)."""
        undocumented = [n for n, f in self.config_class.model_fields.items()
                        if n != "plugin" and not f.description]
        assert not undocumented, f"fields without a docstring: {undocumented}"
        assert (self.config_class.__doc__ or "").strip(), "the config class needs a docstring"

    def test_config_is_strict_frozen_and_round_trips(self, config: StageConfig) -> None:
        """Unknown fields are errors, instances are immutable, dumps validate back."""
        from pydantic import ValidationError

        with pytest.raises(ValidationError):
            self.config_class(**config.model_dump(), no_such_field_xyz=1)
        name = next((n for n in self.config_class.model_fields if n != "plugin"), "plugin")
        with pytest.raises((ValidationError, TypeError, AttributeError)):
            setattr(config, name, getattr(config, name))
        again = self.config_class.model_validate(json.loads(config.model_dump_json()))
        assert again == config

    def test_config_pickles(self, config: StageConfig) -> None:
        """Configs cross process boundaries (executors, multiprocessing) by pickle."""
        assert pickle.loads(pickle.dumps(config)) == config

    def test_schema_exports(self) -> None:
        """The JSON schema forbids extra keys and pins the plugin key."""
        schema = self.config_class.model_json_schema()
        assert schema.get("additionalProperties") is False
        assert self.key in json.dumps(schema["properties"]["plugin"])

    def test_optional_dependencies_have_an_install_hint(self) -> None:
        """A plugin with optional requirements says how to install them."""
        if self.config_class.requires:
            assert self.config_class.install_hint, "requires is set but install_hint is empty"

    def test_found_through_its_entry_point(self) -> None:
        """The entry point loads, registers the key, and ``photonpano plugins`` lists it."""
        if self.entry_point is None:
            pytest.skip("entry_point not set")
        import importlib.metadata

        from photonpano.host import GROUP, PluginHost

        names = {ep.name for ep in importlib.metadata.entry_points(group=GROUP)}
        assert self.entry_point in names, \
            f"no entry point {self.entry_point!r} in group {GROUP!r} (installed?)"
        host = PluginHost()
        assert self.entry_point not in host.broken, host.broken.get(self.entry_point)
        assert host.registry(self.config_class.stage).get(self.key) is not None
        info = next(i for i in host.plugin_infos() if i.key == self.key)
        assert info.stage == self.config_class.stage
        assert info.status == "ok" or info.status.startswith("unavailable"), info.status
        assert info.distribution not in ("?", "(registered in code)")

    def test_selectable_in_a_spec(self, config: StageConfig) -> None:
        """A spec naming the plugin validates into this config class."""
        if self.entry_point is None:
            pytest.skip("entry_point not set")
        from photonpano.host import PluginHost
        from photonpano.spec import validate_spec

        stage = self.config_class.stage
        data: dict[str, Any] = {"source": {"plugin": "simulate", "frames": 1000}}
        data[stage] = config.model_dump(mode="json")
        spec = validate_spec(data, PluginHost(), origin="contract")
        assert type(getattr(spec, stage)) is self.config_class or \
            type(getattr(spec, stage)).__name__ == self.config_class.__name__

    def test_registration_imports_no_heavy_module(self) -> None:
        """Importing the entry-point module (registration) leaves heavy modules unimported."""
        module = self.config_class.__module__
        code = (f"import sys, importlib; importlib.import_module({module!r}); "
                f"print(sorted(m for m in {self.heavy_modules!r} if m in sys.modules))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        assert out.strip() == "[]", f"{module} imports {out.strip()} at registration; import them in build()"


# --- stage contracts --------------------------------------------------------------------


class LocatorContract(PluginContract):
    """The locator contract (see :meth:`photonpano.stages.Locator.register_pairs`).

    Class attributes (besides :class:`PluginContract`'s):
        motion: the warps the locator must recover on synthetic frames: ``"translation"``
            (a sub-pixel shift), ``"similarity"`` (shift, rotation, scale) or
            ``"homography"`` (adds perspective).
        tolerance_px: largest accepted mean corner error in pixels.
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
        """Pair (a, b) gives the map of b's pixels to a's, pixel centres at integers."""
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


class SourceContract(PluginContract):
    """The source contract (see :class:`photonpano.stages.PhotonSource`).

    Override :meth:`make_config` to create the capture the config points at (use
    ``tmp_path_factory``); the capture should hold at least 64 frames.
    """

    def test_describes_itself(self, built: Any) -> None:
        """Positive sizes, exposure and rate; ``describe()`` is JSON-ready."""
        from photonpano.stages import PhotonSource

        assert isinstance(built, PhotonSource)
        assert built.n_frames > 0 and built.height > 0 and built.width > 0
        assert built.exposure_s > 0 and built.frame_rate_hz > 0
        json.dumps(built.describe())
        if built.ground_truth is not None:
            assert built.ground_truth.shape == (built.n_frames, 3, 3)
            assert built.ground_truth.dtype == np.float64

    def test_sum_ranges_shapes_and_additivity(self, built: Any) -> None:
        """(B, H, W) sums; the sum over a range equals the sums over its halves."""
        t = min(built.n_frames, 64) // 2 * 2
        edges = np.array([0, t // 2, t], np.int64)
        counts = built.sum_ranges(edges)
        kind = getattr(built, "kind", "binary")
        assert counts.shape == (2, built.height, built.width)
        if kind == "binary":
            assert counts.dtype == np.uint16
            assert counts.max() <= t // 2 and counts.min() >= 0
        whole = built.sum_ranges(np.array([0, t], np.int64))
        np.testing.assert_allclose(whole[0].astype(np.float64), counts.sum(0, dtype=np.float64), rtol=1e-5)


class ResamplerContract(PluginContract):
    """The resampler contract (see :meth:`photonpano.stages.Resampler.groups`)."""

    def test_groups_are_valid_on_every_level(self, built: Any) -> None:
        """References strictly increase and lie inside their groups, within the capture."""
        n, m = 5000, 250
        for level in (1, 2, 3):
            groups = built.groups(n, m, level)
            assert len(groups) >= 2
            assert groups.start.min() >= 0 and groups.stop.max() <= n
            assert np.all(np.diff(groups.reference) > 0)
            for name in ("start", "stop", "reference"):
                assert getattr(groups, name).dtype == np.int64

    def test_too_short_capture_is_a_value_error(self, built: Any) -> None:
        """Fewer than 2 * group_size frames raise ValueError (the documented error)."""
        with pytest.raises(ValueError):
            built.groups(10, 500, 1)


class MergerContract(PluginContract):
    """The merger contract (see :meth:`photonpano.stages.Merger.merge`), on :func:`tiny_capture`."""

    def test_merges_groups_with_documented_types(self, built: Any) -> None:
        """(G, H, W) float32 flux/frames, uint8 images, bool masks; trusted flux is finite."""
        from photonpano.stages import Groups

        source = tiny_capture()
        n = source.n_frames
        starts = np.arange(0, n, 300, dtype=np.int64)
        groups = Groups(start=starts, stop=np.minimum(starts + 300, n), reference=starts + 150)
        merged = built.merge(source, np.repeat(np.eye(3)[None], n, axis=0), groups)
        g, h, w = len(groups), source.height, source.width
        kinds = (("flux", np.float32), ("frames", np.float32), ("images", np.uint8), ("masks", np.bool_))
        for name, dtype in kinds:
            arr = getattr(merged, name)
            assert arr.shape == (g, h, w) and arr.dtype == dtype, f"{name}: {arr.shape} {arr.dtype}"
        assert merged.masks.mean() > 0.5
        assert np.all(np.isfinite(merged.flux[merged.masks]))
        assert np.all(merged.flux[merged.masks] >= 0)


class InterpolatorContract(PluginContract):
    """The interpolator contract (see :meth:`photonpano.stages.Interpolator.interpolate`)."""

    def test_shapes_and_normalisation(self, built: Any) -> None:
        """(T, 3, 3) float64 with ``H[2, 2] == 1`` from a few keyframes."""
        from photonpano import geometry

        keyframes = np.array([100, 300, 500, 700], np.int64)
        h = geometry.translation(0.0, 0.0)[None].repeat(4, 0)
        h[:, 0, 2] = [0.0, 2.0, 4.0, 6.0]
        out = built.interpolate(keyframes, h, 800)
        assert out.shape == (800, 3, 3) and out.dtype == np.float64
        np.testing.assert_allclose(out[:, 2, 2], 1.0)

    def test_constant_motion_stays_constant(self, built: Any) -> None:
        """Identical keyframe homographies interpolate to that homography everywhere."""
        from photonpano import geometry

        keyframes = np.array([100, 300, 500, 700], np.int64)
        h = np.repeat(geometry.translation(1.5, -0.5)[None], 4, axis=0)
        out = built.interpolate(keyframes, h, 800)
        np.testing.assert_allclose(out, np.repeat(h[:1], 800, axis=0), atol=1e-6)


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
class PoseEstimatorContract(PluginContract):
    """The pose estimator contract (see :meth:`photonpano.stages.PoseEstimator.estimate`).

    Runs the estimator on :meth:`make_capture` (default: a small ``simulate3d`` room of
    ``capture_frames`` frames with ground-truth poses and intrinsics) and checks the
    documented shapes, that registered poses are rigid and near the truth, and that a
    capture too short to register is a :class:`~photonpano.errors.StageError`. Set
    ``config_kwargs`` so that ``capture_frames`` frames are enough for the plugin.
    """

    capture_frames: ClassVar[int] = 4000
    max_ate_m: ClassVar[float] = 0.02
    """Largest acceptable camera-centre RMS error after similarity alignment, metres."""

    @classmethod
    def make_capture(cls, frames: int) -> Any:
        """Return a capture with ``ground_truth_poses`` and ``intrinsics`` (default: ``simulate3d``)."""
        from photonpano.plugins.sources.simulate3d import Simulate3DConfig

        return Simulate3DConfig(frames=frames, height=128, width=248, focal_px=210.0).build()

    @pytest.fixture(scope="class")
    @classmethod
    def estimated(cls, built: Any, tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any]:
        """``(capture, PoseResult)`` of one run with the true intrinsics."""
        capture = cls.make_capture(cls.capture_frames)
        return capture, built.estimate(capture, capture.intrinsics, tmp_path_factory.mktemp("pose"))

    def test_result_shapes_and_rigid_poses(self, estimated: tuple[Any, Any]) -> None:
        """(T, 4, 4) float64 poses with rotation blocks orthonormal, last rows (0, 0, 0, 1)."""
        capture, result = estimated
        poses = result.poses
        assert poses.shape == (capture.n_frames, 4, 4) and poses.dtype == np.float64
        ok = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
        assert ok.mean() > 0.9, "most binary frames should get a pose"
        rot = poses[ok, :3, :3]
        eye = np.broadcast_to(np.eye(3), rot.shape)
        np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), eye, atol=1e-6)
        np.testing.assert_array_equal(poses[ok, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (int(ok.sum()), 4)))
        assert result.exposure_poses.shape == (len(result.exposure_frames), 4, 4)
        assert result.exposure_frames.dtype == np.int64
        assert result.points.ndim == 2 and result.points.shape[1] == 3
        assert len(result.points) == len(result.colors)

    def test_poses_match_ground_truth(self, estimated: tuple[Any, Any]) -> None:
        """Camera centres within ``max_ate_m`` of the truth after a similarity alignment."""
        from photonpano.pose import absolute_trajectory_error

        capture, result = estimated
        assert absolute_trajectory_error(result.poses, capture.ground_truth_poses) < self.max_ate_m

    def test_too_short_capture_is_a_stage_error(self, built: Any, tmp_path: Any) -> None:
        """A capture of a few frames fails with a one-line StageError."""
        from photonpano.errors import StageError

        capture = self.make_capture(64)
        with pytest.raises(StageError):
            built.estimate(capture, capture.intrinsics, tmp_path)
