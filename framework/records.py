"""The frozen records that stages, level schemes and observers exchange.

Shapes follow ``docs/conventions.md``: ``T`` binary frames, ``G`` groups (virtual
exposures), ``P`` registrations, ``H`` x ``W`` frame pixels, ``Hc`` x ``Wc`` canvas
pixels. Homographies map pixel coordinates (x right, y down, pixel centres at integers).
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .types import check_shape

__all__ = ["Groups", "MergedFrames", "PairRegistrations", "Panorama", "Canvas", "LocateResult", "LevelResult"]


@dataclass(frozen=True)
class Groups:
    """The virtual exposures of one level.

    Attributes:
        start: (G,) int64 first binary frame of each group.
        stop: (G,) int64 one past the last frame of each group.
        reference: (G,) int64 frame whose pixel grid the group is merged into and whose
            homography the locator estimates; strictly increasing.
    """

    start: NDArray[np.int64]
    stop: NDArray[np.int64]
    reference: NDArray[np.int64]

    def __post_init__(self) -> None:
        g = check_shape(self.reference, "G", name="Groups.reference")["G"]
        check_shape(self.start, "G", name="Groups.start", G=g)
        check_shape(self.stop, "G", name="Groups.stop", G=g)
        if g and not (np.all(self.start <= self.reference) and np.all(self.reference < self.stop)):
            raise ValueError("Groups: each reference frame must lie inside its group")
        if np.any(np.diff(self.reference) <= 0):
            raise ValueError("Groups: reference frames must be strictly increasing")

    def __len__(self) -> int:
        return len(self.reference)

    def select(self, index: NDArray[np.int64]) -> "Groups":
        """Return the groups ``index`` ((K,) int64, increasing) as a new :class:`Groups`."""
        return Groups(self.start[index], self.stop[index], self.reference[index])


_identity_lock = threading.Lock()
_next_identity = 0


@dataclass(frozen=True)
class MergedFrames:
    """Merged virtual exposures, each in the pixel grid of its group's reference frame.

    Attributes:
        flux: (G, H, W) float32 linear flux in photons/s; NaN where unobserved.
        frames: (G, H, W) float32 number of binary frames behind each pixel.
        images: (G, H, W) uint8 tone-mapped sRGB images for the locator.
        masks: (G, H, W) bool pixels observed by enough frames to be trusted.
        ids: optional (G,) int64 content identities from :meth:`new_ids`, given by a
            producer that knows when a frame's content is new (the pairwise scheme's
            ring of merged frames): equal ids mean identical frames, in this process.
            Without them (None), :meth:`content_key` digests the pixels. The ids also
            name the frames for a locator (:meth:`frame_ids`): its pairs are pairs of ids.
        exposure_s: the binary frame exposure in seconds when ``flux`` is the MLE of
            binary frames (binomial noise: a locator may register
            :func:`~photonpano.binomial.stabilised_detections`), None for intensity frames.
    """

    flux: NDArray[np.float32]
    frames: NDArray[np.float32]
    images: NDArray[np.uint8]
    masks: NDArray[np.bool_]
    ids: NDArray[np.int64] | None = None
    exposure_s: float | None = None

    def __len__(self) -> int:
        return len(self.flux)

    @staticmethod
    def concat(*parts: MergedFrames) -> MergedFrames:
        """Return the merged frames of ``parts`` one after another (with ids if every part has them).

        Their ``exposure_s`` is the parts' where all agree, else None.
        """
        fields = ("flux", "frames", "images", "masks")
        ids = np.concatenate([p.ids for p in parts]) if all(p.ids is not None for p in parts) else None
        flux, frames, images, masks = (np.concatenate([getattr(p, f) for p in parts]) for f in fields)
        exposures = {p.exposure_s for p in parts}
        return MergedFrames(flux, frames, images, masks, ids=ids,
                            exposure_s=exposures.pop() if len(exposures) == 1 else None)

    def frame_ids(self) -> NDArray[np.int64]:
        """Return the (G,) int64 names of the frames: :attr:`ids`, or positions ``0..G-1`` without ids.

        A locator's pairs name frames by these (:meth:`~photonpano.locator.Locator.register_pairs`).
        """
        return self.ids if self.ids is not None else np.arange(len(self), dtype=np.int64)

    def take(self, index: NDArray[np.int64]) -> MergedFrames:
        """Return frames ``index`` ((K,) int positions), with their ids when these frames carry ids."""
        ids = None if self.ids is None else self.ids[index]
        return MergedFrames(self.flux[index], self.frames[index], self.images[index], self.masks[index], ids=ids,
                            exposure_s=self.exposure_s)

    @staticmethod
    def new_ids(count: int) -> NDArray[np.int64]:
        """Return ``count`` content identities never returned before in this process ((count,) int64)."""
        global _next_identity
        with _identity_lock:
            first, _next_identity = _next_identity, _next_identity + count
        return np.arange(first, first + count, dtype=np.int64)

    def content_key(self, index: int, *, flux: bool = False) -> bytes:
        """Return a cache key of frame ``index``'s content: equal keys mean identical frames.

        Args:
            index: frame index.
            flux: whether the data to be cached derives from the float32 flux (digested
                then) rather than from the uint8 image and the mask; ignored with ``ids``,
                which identify every array of a frame.

        Returns:
            With ``ids``: ``b"id"`` and the frame's id (10 bytes). Otherwise the 16-byte
            BLAKE2b digest of the arrays (about 0.1 ms per 127 x 248 frame).
        """
        if self.ids is not None:
            return b"id" + int(self.ids[index]).to_bytes(8, "little", signed=True)
        digest = hashlib.blake2b(digest_size=16)
        if flux:
            digest.update(np.ascontiguousarray(self.flux[index]).data)
        else:
            digest.update(np.ascontiguousarray(self.images[index]).data)
            digest.update(np.ascontiguousarray(self.masks[index]).data)
        return digest.digest()


@dataclass(frozen=True)
class PairRegistrations:
    """Homographies between pairs of merged frames.

    Attributes:
        homographies: (P, 3, 3) float64; entry p maps pixel coordinates of merged frame
            ``pairs[p, 1]`` to those of merged frame ``pairs[p, 0]``.
        matches: (P,) int64 tentative correspondences (0 for direct methods).
        inliers: (P,) int64 correspondences consistent with the homography.
        ok: (P,) bool False where the pair failed to register (its homography is then
            meaningless and is bridged by the framework).
    """

    homographies: NDArray[np.float64]
    matches: NDArray[np.int64]
    inliers: NDArray[np.int64]
    ok: NDArray[np.bool_]

    def __post_init__(self) -> None:
        p = check_shape(self.homographies, "P 3 3", name="PairRegistrations.homographies")["P"]
        for name in ("matches", "inliers", "ok"):
            check_shape(getattr(self, name), "P", name=f"PairRegistrations.{name}", P=p)

    def __len__(self) -> int:
        return len(self.ok)

    def take(self, index: Any) -> PairRegistrations:
        """Return the registrations ``index`` (an index array, mask or slice)."""
        return PairRegistrations(*(getattr(self, f)[index] for f in _REGISTRATION_FIELDS))

    def with_ok(self, ok: NDArray[np.bool_]) -> PairRegistrations:
        """Return the same registrations with ``ok`` replaced ((P,) bool)."""
        return PairRegistrations(self.homographies, self.matches, self.inliers, ok)

    @staticmethod
    def concat(*parts: PairRegistrations) -> PairRegistrations:
        """Return the registrations of ``parts`` one after another (none: an empty record)."""
        if not parts:
            return PairRegistrations(np.zeros((0, 3, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                                     np.zeros(0, bool))
        return PairRegistrations(*(np.concatenate([getattr(p, f) for p in parts]) for f in _REGISTRATION_FIELDS))


_REGISTRATION_FIELDS = ("homographies", "matches", "inliers", "ok")


@dataclass(frozen=True)
class Panorama:
    """A panorama canvas.

    Attributes:
        flux: (Hc, Wc) float32 linear flux in photons/s; NaN where no frame looked
            ((Hc, Wc, C) from compositors of C channels, e.g. colour).
        frames: (Hc, Wc) float32 number of binary frames behind each canvas pixel
            (weighted by the compositor's kernel; (Hc, Wc, C) with channels).
        homographies: (T, 3, 3) float64 frame-to-canvas homographies (canvas pixels,
            including the super-resolution scale).
        colour: (Hc, Wc, 3) float32 flux in photons/s behind the R, G, B filters of a
            colour-filtered sensor, composited in the same pass as ``flux`` (see
            :meth:`~photonpano.stages.SourceConfig.panorama_compositor`); NaN where a
            channel saw nothing; None without colour.
        moving: (Hc, Wc) bool canvas pixels where a robust compositor left out the
            observations of some virtual exposures (a moving object; see
            :mod:`photonpano.robust_merge`); None from a compositor that merges every photon.
        rejected: (K, Hc, Wc) bool which of the K virtual exposures fed the robust
            ``flux-canvas`` left out at each canvas pixel (the mosaic levels' template:
            where the mover was during each exposure); None from other compositors.
        exposure_ranges: (K, 2) int64 first binary frame and end of those K exposures.
    """

    flux: NDArray[np.float32]
    frames: NDArray[np.float32]
    homographies: NDArray[np.float64]
    colour: NDArray[np.float32] | None = None
    moving: NDArray[np.bool_] | None = None
    rejected: NDArray[np.bool_] | None = None
    exposure_ranges: NDArray[np.int64] | None = None


@dataclass(frozen=True)
class Canvas:
    """Where a compositor paints.

    Attributes:
        height: canvas height Hc in pixels.
        width: canvas width Wc in pixels.
        homographies: (T, 3, 3) float64 frame-to-canvas homographies of every binary
            frame (canvas pixel centres at integers, x right, y down).
    """

    height: int
    width: int
    homographies: NDArray[np.float64]

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``."""
        return self.height, self.width


@dataclass(frozen=True)
class LocateResult:
    """What a level scheme's locate step found (see :mod:`photonpano.schemes`).

    Attributes:
        keyframes: (G, 3, 3) float64 homographies of the groups' reference frames
            (panorama coordinates of the current estimate).
        registrations: the registrations behind them: pairs of merged frames
            (``pair_index``), or each merged frame against the panorama (``pair_index``
            None: registration g belongs to group g).
        pair_index: (P, 2) int64 merged-frame indices ``(a, b)`` of each pair, the G - 1
            consecutive pairs first; None for registrations against the panorama.
        merged: the level's merged frames if they were asked for (dumps), else None.
        merge_s: wall time spent merging, in seconds (part of the locate step's time).
        locator_cache: feature-cache statistics of the scheme's locators, or None.
        crosscheck: held-out registrations of consecutive merged frames directly against
            each other (not used for the keyframes; see :mod:`photonpano.uncertainty`),
            if the level was asked for them, else None.
        crosscheck_index: (C, 2) int64 merged-frame indices ``(a, b)`` of each
            held-out registration (``b = a + 1``), or None.
        chain: held-out registrations of merged frames far apart, each link's later frame
            against its earlier (:mod:`photonpano.long_pairs`), where the crosscheck was
            asked for and the level has at least 8 groups, else None.
        chain_index: (P, 3) int64 ``(chain, a, b)`` of each link (merged-frame indices), or None.
        check: the figures of the binned check of the scheme's registrations
            (:meth:`~photonpano.schemes.check.LevelCheck.figures`; ``run.json``'s
            ``registration_check``), or None where none ran.
        movers: the mosaic scheme's mover rejection at this level (``run.json``'s
            ``movers``: ``engaged``, whether a detection ran here, and the fraction of
            the template's covered canvas its robust merge left out; see
            :mod:`photonpano.schemes.mosaic`), or None where it is off.
        information: (G, 8, 8) float64 information of each keyframe's registration about
            the 8 parameters of its homography about the frame centre, in sensor pixels
            (:func:`~photonpano.information.homography_information`; zero where the
            registration failed), which lets the level loop correct each shift once the
            shape is smoothed (:func:`~photonpano.information.conditional_shift`); None
            where the scheme does not say (pairwise levels).
        template_bias: the mosaic scheme's correction of its registrations for the
            template's own error (``run.json``'s ``levels[k].template_bias``: ``knots``,
            ``prior_px`` (p1..p8), ``correction_px``; :mod:`photonpano.schemes.template_bias`), or
            None where none was made.
    """

    keyframes: NDArray[np.float64]
    registrations: PairRegistrations
    pair_index: NDArray[np.int64] | None
    merged: MergedFrames | None = None
    merge_s: float = 0.0
    locator_cache: dict[str, int] | None = None
    crosscheck: PairRegistrations | None = None
    crosscheck_index: NDArray[np.int64] | None = None
    chain: PairRegistrations | None = None
    chain_index: NDArray[np.int64] | None = None
    check: dict[str, Any] | None = None
    movers: dict[str, Any] | None = None
    information: NDArray[np.float64] | None = None
    template_bias: dict[str, Any] | None = None

    @property
    def primary(self) -> NDArray[np.bool_]:
        """(P,) bool: the registrations each keyframe depends on.

        Consecutive pairs, or all registrations against the panorama; not the
        longer-offset pairs.
        """
        if self.pair_index is None:
            return np.ones(len(self.registrations.ok), bool)
        primary: NDArray[np.bool_] = self.pair_index[:, 1] - self.pair_index[:, 0] == 1
        return primary

    def failed_groups(self) -> NDArray[np.int64]:
        """(F,) int64 groups whose primary registration failed and was bridged.

        For a pair, its first group.
        """
        failed = self.primary & ~self.registrations.ok
        return np.flatnonzero(failed) if self.pair_index is None else self.pair_index[failed, 0]


@dataclass(frozen=True)
class LevelResult:
    """What one level produced, as observers receive it.

    Attributes:
        level: 1-based level number.
        scheme: the level scheme that located it (``"pairwise"`` or ``"mosaic"``).
        groups: the level's virtual exposures.
        located: the locate step's :class:`LocateResult` (its keyframes in the
            coordinates of the estimate the level started from).
        homographies: (T, 3, 3) float64 per-frame homographies after the level, in
            panorama coordinates: pixel coordinates of the middle binary frame ``T // 2``
            (its homography is the identity), as ``homographies.npy`` before the canvas
            shift.
        timings_s: wall time of each step in seconds (resample, merge, locate, interpolate).
        rejected_keyframes: keyframes whose update was implausible and was bridged from
            their neighbours instead.
        uncorrected: (T, 3, 3) float64 the homographies before the correction of the shape
            drift (:func:`~photonpano.long_pairs.correct_shape_drift`; same coordinates),
            None where it did not run.
        shape_drift_px: the largest move of a frame by that correction (mean corner
            distance, pixels), None where it did not run.
    """

    level: int
    scheme: str
    groups: Groups
    located: LocateResult
    homographies: NDArray[np.float64]
    timings_s: dict[str, float] = field(default_factory=dict)
    rejected_keyframes: int = 0
    uncorrected: NDArray[np.float64] | None = None
    shape_drift_px: float | None = None

    @property
    def merged(self) -> MergedFrames | None:
        """The level's merged frames, if kept for dumps (``outputs.merged_frames``)."""
        return self.located.merged

    def statistics(self) -> dict[str, Any]:
        """Return JSON-ready per-level statistics.

        ``failed_pairs`` counts primary registrations (consecutive pairs, or merged
        frames against the panorama) that failed and were bridged; ``extra_pairs_used``
        counts longer-offset pairs that passed the checks; matches and inliers are over
        the primary registrations.
        """
        p, primary = self.located.registrations, self.located.primary
        return {
            "level": self.level,
            "scheme": self.scheme,
            "groups": len(self.groups),
            "pairs": len(p.ok),
            "failed_pairs": int((~p.ok[primary]).sum()),
            "failed_pair_indices": self.located.failed_groups().tolist(),
            "extra_pairs_used": int(p.ok[~primary].sum()),
            "median_matches": float(np.median(p.matches[primary])) if primary.any() else 0.0,
            "median_inliers": float(np.median(p.inliers[primary])) if primary.any() else 0.0,
            "min_inliers": int(p.inliers[primary].min()) if primary.any() else 0,
            "rejected_keyframes": self.rejected_keyframes,
            "shape_drift_px": self.shape_drift_px,
            "timings_s": self.timings_s,
        }
