"""Stage interfaces: one config base class and one working class per stage kind.

A plugin registers *config classes* (cheap pydantic models, importable without heavy
dependencies). The pipeline validates a spec into those configs and calls ``build()`` on
each to get the working stage object. Stages exchange the frozen records of
:mod:`photonpano.records` (re-exported here).

Stage kinds, in pipeline order: source, resampler, merger, locator, interpolator,
compositor; and the experimental pose_estimator (6-DoF camera poses instead of
homographies, see :mod:`photonpano.pose`).
"""

from __future__ import annotations

import abc
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Callable, ClassVar

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from .config import StageConfig
from .locator import Locator, LocatorConfig, LocatorContext
from .records import Groups, MergedFrames, PairRegistrations

if TYPE_CHECKING:
    from .records import Canvas, Panorama

__all__ = ["StageConfig", "SourceConfig", "ResamplerConfig", "MergerConfig", "LocatorConfig", "InterpolatorConfig",
           "PhotonSource", "Groups", "Resampler", "MergedFrames", "Merger", "PairRegistrations", "Locator",
           "LocatorContext", "Interpolator", "CompositorConfig", "Compositor", "PoseEstimatorConfig", "PoseEstimator",
           "STAGES"]


# --- source: where binary frames come from -----------------------------------------


class SourceConfig(StageConfig):
    """Config base of sources; ``build()`` returns a :class:`PhotonSource`."""

    stage: ClassVar[str] = "source"

    def panorama_compositor(self, build: Callable[[], Compositor]) -> Compositor:
        """The panorama stage's compositor for captures of this config.

        Args:
            build: builds the spec's compositor (its config's ``build``).

        Returns:
            ``build()`` by default; sources whose panorama holds more than the flux wrap
            it (a colour-filtered sensor's colour planes in the same pass, see
            :mod:`photonpano.plugins.compositors.colour`).
        """
        return build()


class PhotonSource(abc.ABC):
    """A capture of binary frames (a photon cube) with random access by frame range.

    Attributes:
        n_frames: number of binary frames T.
        height: frame height H in pixels.
        width: frame width W in pixels.
        exposure_s: exposure time tau of one binary frame, in seconds.
        frame_rate_hz: binary frames per second.
        ground_truth: (T, 3, 3) float64 true frame-to-scene homographies, or None.
        scene_flux: (Hs, Ws) float32 true flux of the scene in photons/s, or None; its
            pixel grid is ``scene_pitch`` times finer than the coordinates
            ``ground_truth`` maps to (pixel centres at integers, see
            :func:`~photonpano.geometry.scale_matrix`).
        scene_pitch: scene pixels per ground-truth unit (1.0: ``scene_flux`` is in the
            coordinates ``ground_truth`` maps to; 2.0 for a sensor whose pixels are
            point samples 2 scene pixels apart).
        name: a short description for logs and ``run.json``.
        kind: ``"binary"`` (the default): frames are binary and :meth:`sum_ranges`
            returns (B, H, W) uint16 detection counts; ``"intensity"``: frames are
            linear intensities (conventional high-speed video, see
            :mod:`photonpano.intensity`) and :meth:`sum_ranges` returns (B, H, W)
            float32 sums of linear intensity. Mergers that only handle one kind check it.
        frame_step: :meth:`sum_ranges` is cheapest for ranges whose edges are multiples
            of this many frames (1: any range; a capture whose photons were counted in
            blocks, see :class:`photonpano.budget.grid.BinnedBlocks`); callers that choose
            their ranges freely (sub-batches) put their edges there.
    """

    n_frames: int
    height: int
    width: int
    exposure_s: float
    frame_rate_hz: float
    ground_truth: NDArray[np.float64] | None = None
    scene_flux: NDArray[np.float32] | None = None
    scene_pitch: float = 1.0
    name: str = ""
    kind: str = "binary"
    frame_step: int = 1

    @abc.abstractmethod
    def sum_ranges(self, edges: NDArray[np.int64]) -> NDArray[np.uint16] | NDArray[np.float32]:
        """Count detections per pixel over consecutive frame ranges.

        Args:
            edges: (B + 1,) strictly increasing frame indices within ``[0, T]``.

        Returns:
            (B, H, W) uint16 counts; range ``b`` covers frames ``edges[b]:edges[b+1]``
            (float32 sums of linear intensity for ``kind == "intensity"`` sources).
        """

    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable summary of the capture for ``run.json``."""
        return {"name": self.name, "frames": self.n_frames, "height": self.height,
                "width": self.width, "exposure_s": self.exposure_s,
                "frame_rate_hz": self.frame_rate_hz}


# --- resampler: which frames form each virtual exposure ---------------------------


class ResamplerConfig(StageConfig):
    """Config base of resamplers; ``build()`` returns a :class:`Resampler`."""

    stage: ClassVar[str] = "resampler"


class Resampler(abc.ABC):
    """Chooses the groups of binary frames (virtual exposures) of each level."""

    @abc.abstractmethod
    def groups(self, n_frames: int, group_size: int, level: int) -> Groups:
        """Return the groups of ``level`` (1-based) for a capture of ``n_frames`` frames.

        Args:
            n_frames: number of binary frames T.
            group_size: frames per group m.
            level: 1 for the first level.

        Raises:
            ValueError: if the capture holds fewer than ``2 * group_size`` frames, or has
                no room for ``level`` (a short clip). The pipeline then runs the levels
                before it and notes so; at level 1 the message is the run's error.
        """


# --- merger: virtual exposures from photons -------------------------------------


class MergerConfig(StageConfig):
    """Config base of mergers; ``build()`` returns a :class:`Merger`."""

    stage: ClassVar[str] = "merger"


class Merger(abc.ABC):
    """Warps and merges the binary frames of each group into one virtual exposure."""

    @abc.abstractmethod
    def merge(self, source: PhotonSource, homographies: NDArray[np.float64], groups: Groups,
              progress: Any = None, executor: Any = None) -> MergedFrames:
        """Merge every group.

        Args:
            source: the capture.
            homographies: (T, 3, 3) float64 current frame-to-panorama homographies.
            groups: the groups to merge.
            progress: optional callable ``progress(n)`` advanced by groups done.
            executor: optional :class:`~photonpano.executor.Executor` to run
                independent groups on (None: serially).

        Returns:
            One merged frame per group, in its reference frame's pixel grid.
        """


# --- locator: registration of merged frames (the contract is :mod:`photonpano.locator`) ----------


# --- interpolator: homographies for every binary frame ---------------------------


class InterpolatorConfig(StageConfig):
    """Config base of interpolators; ``build()`` returns an :class:`Interpolator`."""

    stage: ClassVar[str] = "interpolator"


class Interpolator(abc.ABC):
    """Interpolates homographies known at some frames to every binary frame."""

    @abc.abstractmethod
    def interpolate(self, keyframes: NDArray[np.int64], homographies: NDArray[np.float64],
                    n_frames: int, groups: Groups | None = None) -> NDArray[np.float64]:
        """Interpolate ``homographies`` known at ``keyframes`` to frames ``0..n_frames-1``.

        Args:
            keyframes: (G,) int64 strictly increasing frame indices, G >= 1.
            homographies: (G, 3, 3) float64 homographies at those frames (from the level
                loop: each keyframe's pose, standing for its group's mean pose, in panorama
                coordinates with the origin at the middle frame's centre, so ``p5, p6``
                are the frame centre's position and ``p1..p4, p7, p8`` its shape;
                :func:`photonpano.levels.estimate_motion`).
            n_frames: number of binary frames T.
            groups: the groups whose merged frames gave the keyframes (their
                ``reference`` equals ``keyframes``), for interpolators that model a
                keyframe as the average over its group's frames; None if unknown.

        Returns:
            (T, 3, 3) float64, normalised (``H[2, 2] == 1``); frames before the first
            and after the last keyframe get extrapolated values.
        """

    def warm_up(self) -> None:
        """Load what the first :meth:`interpolate` call needs (e.g. import its libraries).

        Called by the level loop in a background thread while the photons are counted
        and level 1 registers, so that a slow first import is not on the run's critical
        path; errors are ignored there (the first real call raises them). The default
        does nothing.
        """


# --- compositor: the panorama from every binary frame --------------------------------


class CompositorConfig(StageConfig):
    """Config base of compositors; ``build()`` returns a :class:`Compositor`."""

    stage: ClassVar[str] = "compositor"
    scale: Annotated[float, Field(gt=0, le=8)] = 1.0
    """Super-resolution scale of the panorama canvas (canvas pixels per frame pixel)."""


class Compositor(abc.ABC):
    """Turns binary frames and their homographies into a panorama, a sub-batch at a time.

    The framework (:func:`photonpano.compose.compose`) calls :meth:`prepare` once, then :meth:`feed` with
    sub-batches of frames in any order (each frame exactly once), then :meth:`finish`; memory is bounded by
    the canvas, not by the capture (as OpenCV's ``detail::Blender``: prepare / feed / blend). To use several
    threads, the framework feeds :meth:`fork` copies from other threads and :meth:`join` s them before
    :meth:`finish`.

    Attributes:
        scale: super-resolution scale (canvas pixels per frame pixel), from the config.
    """

    scale: float = 1.0

    @abc.abstractmethod
    def prepare(self, canvas: Canvas, source: PhotonSource) -> None:
        """Start a panorama on ``canvas`` (empty accumulators) for frames of ``source``.

        Args:
            canvas: the canvas: its shape and the (T, 3, 3) frame-to-canvas homographies.
            source: the capture (``kind``, ``exposure_s``, frame shape; compositors that
                read the source their own way use it in :meth:`read`).
        """

    def read(self, source: PhotonSource, edges: NDArray[np.int64]) -> NDArray[Any]:
        """Return the (B, H, W) sums of frame ranges ``edges`` that :meth:`feed` takes.

        The default is ``source.sum_ranges(edges)``; a compositor that needs other
        per-pixel sums (raw colour-filtered pixels, say) overrides it.
        """
        return source.sum_ranges(edges)

    @abc.abstractmethod
    def feed(self, counts: NDArray[Any], n_frames: NDArray[np.int64], homographies: NDArray[np.float64],
             weights: NDArray[np.float32] | None = None) -> None:
        """Add a sub-batch of summed frames.

        Args:
            counts: (B, H, W) detections (uint16, or float32 linear intensity sums for intensity sources),
                each the sum of ``n_frames[b]`` binary frames.
            n_frames: (B,) int64 binary frames behind each count image.
            homographies: (B, 3, 3) float64 frame-to-canvas homographies (canvas pixels, pixel centres at
                integers), one per count image.
            weights: (H, W) float32 weight of each frame pixel in [0, 1] (0 leaves the pixel out, e.g.
                pixels behind another colour filter); None: all 1.
        """

    def expect_flicker(self, period_frames: float) -> None:
        """Be told, before :meth:`prepare`, that a lamp flickers with this period while the capture runs.

        :func:`~photonpano.flicker.detect_flicker` found it (over part of the scene or all
        of it). A compositor that merges by time (the robust merge of
        :mod:`photonpano.robust_merge`) then cuts the capture at whole periods, so that each
        run of frames sees the lamp's mean level; the default ignores it.

        Args:
            period_frames: the flicker period in binary frames (> 0, not necessarily whole).
        """

    def frame_breaks(self, n_frames: int, frame_step: int = 1) -> NDArray[np.int64] | None:
        """Frame indices where the sub-batches fed to :meth:`feed_ranges` must end (None: anywhere).

        Args:
            n_frames: frames T of the capture.
            frame_step: the source counts frames in blocks of this many (breaks fall on multiples).

        Returns:
            (E,) int64 sorted frame indices in ``(0, T)``, or None.
        """
        return None

    def feed_ranges(self, edges: NDArray[np.int64], counts: NDArray[Any],
                    homographies: NDArray[np.float64]) -> None:
        """Add a sub-batch of summed frames, knowing which frames they are.

        What :func:`~photonpano.compose.compose` calls; the default forgets the frame indices and calls
        :meth:`feed`. A compositor that merges by time (the robust merge of :mod:`photonpano.robust_merge`
        keeps virtual exposures apart) overrides it.

        Args:
            edges: (B + 1,) int64 frame-range edges: count image b is the sum of frames ``edges[b]:edges[b + 1]``.
            counts: (B, H, W) summed frames, as :meth:`feed`'s.
            homographies: (B, 3, 3) float64 frame-to-canvas homographies, as :meth:`feed`'s.
        """
        n_frames: NDArray[np.int64] = np.diff(np.asarray(edges, np.int64)).astype(np.int64)
        self.feed(counts, n_frames, homographies)

    def fork(self) -> Compositor | None:
        """Return an empty compositor on the same canvas to feed from another thread.

        None (the default) means the compositor is fed from one thread only.
        """
        return None

    def join(self, other: Compositor) -> None:
        """Add what a :meth:`fork` copy accumulated (called before :meth:`finish`)."""
        raise NotImplementedError(f"{type(self).__name__}.join")

    @abc.abstractmethod
    def finish(self) -> Panorama:
        """Return the panorama: flux per canvas pixel (NaN where unobserved).

        Returns:
            A :class:`~photonpano.compose.Panorama` on the prepared canvas.
        """


# --- pose estimator (experimental): 6-DoF camera poses ------------------------------


class PoseEstimatorConfig(StageConfig):
    """Config base of pose estimators; ``build()`` returns a :class:`PoseEstimator`."""

    stage: ClassVar[str] = "pose_estimator"
    intrinsics: Path | None = None
    """JSON file with the camera's ``fx``, ``fy``, ``cx``, ``cy`` in pixels (OpenCV convention:
    pixel centres at integers; other keys ignored); none: self-calibration."""


class PoseEstimator(abc.ABC):
    """Estimates a camera-to-world pose for binary frames of a capture (experimental)."""

    @abc.abstractmethod
    def estimate(self, source: PhotonSource, intrinsics: Any, work_dir: Path, progress: Any = None) -> Any:
        """Estimate poses of the capture.

        Args:
            source: the capture.
            intrinsics: a :class:`photonpano.pose.Intrinsics` (pixels, OpenCV convention),
                or None to self-calibrate.
            work_dir: an existing folder for intermediate files (images, databases, models).
            progress: optional ``start_task``-like callable (see :mod:`photonpano.progress`).

        An estimator that also takes ``checkpoints`` gets a run's
        :class:`~photonpano.pose_checkpoints.PoseCheckpoints` (``pose --resume``).

        Returns:
            A :class:`photonpano.pose.PoseResult`.

        Raises:
            StageError: if the capture is too short or too dark to register.
        """


STAGES: dict[str, type[StageConfig]] = {
    "source": SourceConfig,
    "resampler": ResamplerConfig,
    "merger": MergerConfig,
    "locator": LocatorConfig,
    "interpolator": InterpolatorConfig,
    "compositor": CompositorConfig,
    "pose_estimator": PoseEstimatorConfig,
}
"""Stage kind -> config base class, in pipeline order."""
