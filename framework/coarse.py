"""Registration that survives few photons: a check and a fallback on binned flux images.

Features need texture that a merged frame of a few photons per pixel does not show;
the scene's *signal* is still there, spread over many pixels. :class:`CascadeLocator`
wraps the spec's locator at pairwise levels with ``group_size: auto``:

1. every pair the locator registered is **checked** on spatially binned merged frames
   (blocks of ``binning`` pixels, square-root flux, which makes photon noise about
   uniform): the correlation of frame a with frame b warped by the homography must
   reach ``min_correlation``, else the pair counts as failed (a spurious match on
   photon noise correlates near 0);
2. every failed pair is registered **directly** on the binned frames: phase
   correlation for the translation left by the current estimate, then ECC
   (Evangelidis and Psarakis, 2008) for an affine correction, both coarse (binned)
   where the photon counts make the images usable.

The quality figures (correlation per pair, pairs checked out and rescued) are kept for
``run.json`` (:meth:`CascadeLocator.take_statistics`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .adaptive import binned_image, normalised_correlation
from .stages import Locator, MergedFrames, PairRegistrations
from .watchdog import watched

__all__ = ["CascadeLocator", "register_binned", "binned_frame"]


def _in_binned(homography: NDArray[np.float64], factor: int, *, back: bool = False) -> NDArray[np.float64]:
    """A (3, 3) homography of full-resolution pixels in pixels of blocks of ``factor`` (``back``: the reverse).

    Binned pixel ``u`` is centred on full-resolution ``factor * u + (factor - 1) / 2``
    (:func:`~photonpano.adaptive.binned_image`), so ``u = (x + 0.5) / factor - 0.5``:
    :func:`~photonpano.geometry.scale_matrix`'s map, as for ``RegistrationGrid``.
    """
    if factor == 1:
        return homography
    s = geometry.scale_matrix(1.0 / factor)
    return np.linalg.inv(s) @ homography @ s if back else s @ homography @ np.linalg.inv(s)


def binned_frame(flux: NDArray[np.float32], mask: NDArray[np.bool_], factor: int, blur: int = 5
                 ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """A merged frame as a binned, blurred square-root flux image for direct registration.

    Args:
        flux: (H, W) float32 flux in photons/s, NaN where unobserved.
        mask: (H, W) bool trusted pixels.
        factor: binning (pixels per side).
        blur: Gaussian filter size in binned pixels (odd; 1 = none).

    Returns:
        ``(image, valid)``: (H // factor, W // factor) float32 and bool (see
        :func:`~photonpano.adaptive.binned_image`).
    """
    import cv2

    image, valid = binned_image(np.sqrt(np.maximum(flux, 0)), factor, mask)
    if blur > 1:
        image = cv2.GaussianBlur(image, (blur, blur), 0)
        weight = cv2.GaussianBlur(valid.astype(np.float32), (blur, blur), 0)
        image = np.where(valid, image / np.maximum(weight, 1e-6), 0).astype(np.float32)
    return image, valid


def _warp(image: NDArray[np.float32], valid: NDArray[np.bool_], homography: NDArray[np.float64]):
    """Frame b's binned image in frame a's binned grid: ``out(x) = image(inv(H) x)``."""
    import cv2

    h, w = image.shape
    moved = cv2.warpPerspective(image, homography, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
    inside = cv2.warpPerspective(valid.astype(np.uint8), homography, (w, h), flags=cv2.INTER_NEAREST,
                                 borderValue=0) > 0
    return moved, inside


def warped_correlation(a: tuple[NDArray, NDArray], b: tuple[NDArray, NDArray],
                       homography: NDArray[np.float64], factor: int) -> tuple[float, int]:
    """Correlation of binned frame a with binned frame b warped by ``homography`` (b to a, full pixels).

    Returns:
        ``(correlation, overlap)``: Pearson correlation over the binned pixels valid in
        both, and their number.
    """
    moved, inside = _warp(b[0], b[1], _in_binned(homography, factor))
    both = inside & a[1]
    return normalised_correlation(a[0], moved, both), int(both.sum())


def register_binned(a: tuple[NDArray, NDArray], b: tuple[NDArray, NDArray], initial: NDArray[np.float64],
                    factor: int, *, iterations: int = 50) -> tuple[NDArray[np.float64], float, int]:
    """Register two binned frames directly: phase correlation, then affine ECC.

    Args:
        a: :func:`binned_frame` of frame a (the moving image).
        b: :func:`binned_frame` of frame b (the template).
        initial: (3, 3) float64 current estimate mapping b's full-resolution pixels to a's.
        factor: the frames' binning.
        iterations: ECC iterations.

    Returns:
        ``(homography, correlation, overlap)``: (3, 3) float64 mapping b's full-resolution
        pixels to a's, the final correlation (-1 where ECC failed) and the binned pixels
        compared.
    """
    import cv2

    start = _in_binned(initial, factor)
    moved, inside = _warp(b[0], b[1], start)
    h, w = moved.shape
    window = cv2.createHanningWindow((w, h), cv2.CV_32F)
    fill_a = np.where(a[1], a[0], a[0][a[1]].mean() if a[1].any() else 0).astype(np.float32)
    fill_b = np.where(inside, moved, moved[inside].mean() if inside.any() else 0).astype(np.float32)
    (dx, dy), _ = cv2.phaseCorrelate(fill_a - fill_a.mean(), fill_b - fill_b.mean(), window)
    # moved(x) ~ a(x - d): the correction maps moved's pixels to a's by x - d
    warp = np.float32([[1, 0, -dx], [0, 1, -dy]])
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-5)
    try:
        cc, warp = cv2.findTransformECCWithMask(moved, a[0], inside.astype(np.uint8), a[1].astype(np.uint8),
                                                warp, cv2.MOTION_AFFINE, criteria, 1)
    except cv2.error:
        return initial, -1.0, 0
    correction = np.vstack([warp.astype(np.float64), [0, 0, 1]])
    found = geometry.normalize(_in_binned(correction @ start, factor, back=True))
    return found, float(cc), int((inside & a[1]).sum())


class CascadeLocator(Locator):
    """A locator whose registrations are checked, and rescued where they fail, on binned frames.

    Args:
        primary: the spec's built locator (attributes not defined here are its own).
        binning: merged-frame pixels per side of the binned frames (>= 1).
        min_correlation: the binned correlation a registration must reach.
        min_overlap: fraction of binned pixels both frames must share.
    """

    def __init__(self, primary: Locator, binning: int, *, min_correlation: float = 0.4,
                 min_overlap: float = 0.3) -> None:
        self.__dict__["primary"] = primary
        self.factor = max(1, int(binning))
        self.min_correlation = min_correlation
        self.min_overlap = min_overlap
        self._stats = self._empty()
        self._binned: dict[tuple[bytes, bytes], tuple[NDArray[np.float32], NDArray[np.bool_]]] = {}

    @staticmethod
    def _empty() -> dict[str, Any]:
        return {"checked": 0, "rejected_by_check": 0, "rescued": 0, "correlations": []}

    def __getattr__(self, name: str) -> Any:  # only called for attributes not found here
        return getattr(self.__dict__["primary"], name)

    @property
    def executor(self) -> Any:
        """The primary locator's executor (set by the framework)."""
        return self.primary.executor

    @executor.setter
    def executor(self, value: Any) -> None:
        self.primary.executor = value

    def cache_stats(self) -> dict[str, int]:
        """The primary locator's feature-cache counters."""
        return self.primary.cache_stats()

    def reset_cache_stats(self) -> None:
        """Zero the primary locator's counters."""
        self.primary.reset_cache_stats()

    def end_level(self) -> None:
        """Drop the binned frames kept across calls, and the primary locator's cached data."""
        self._binned = {}
        self.primary.end_level()

    def register_pairs(self, merged: MergedFrames, pairs: NDArray[np.int64],
                       initial: NDArray[np.float64]) -> PairRegistrations:
        """Register with the primary locator, then check and rescue on binned frames (see the module).

        The binned frames, then the pairs' checks and rescues, run on the executor's
        threads (OpenCV and the compiled correlation release the GIL); a Dask
        executor's tasks would ship the frames to other processes, so there they run
        here, one after another. Each frame is binned once per content
        (:meth:`~photonpano.records.MergedFrames.content_key`): frames that the previous
        call used are reused, others are dropped.
        """
        from .executor import SerialExecutor

        with watched("locator", self.primary, "register_pairs"):
            found = self.primary.register_pairs(merged, pairs, initial)
        executor = self.executor if getattr(self.executor, "in_process", False) else SerialExecutor()
        frames = [int(i) for i in np.unique(pairs)]
        # a binned frame reads the flux and the mask: key both (one id when the frames carry ids)
        keys = {i: (merged.content_key(i), merged.content_key(i, flux=True)) for i in frames}
        missing = [i for i in frames if keys[i] not in self._binned]
        computed = dict(zip(missing, executor.map(
            lambda i: binned_frame(merged.flux[i], merged.masks[i], self.factor), missing)))
        binned = {i: computed[i] if i in computed else self._binned[keys[i]] for i in frames}
        self._binned = {keys[i]: binned[i] for i in frames}

        def check(p: int) -> tuple[NDArray[np.float64], int, bool, float, bool]:
            """Pair p's (homography, inliers, ok, correlation, rescued)."""
            a, b = binned[int(pairs[p, 0])], binned[int(pairs[p, 1])]
            need = self.min_overlap * max(int(b[1].sum()), 1)
            homography, inliers = found.homographies[p], int(found.inliers[p])
            if found.ok[p]:
                cc, overlap = warped_correlation(a, b, homography, self.factor)
                if cc >= self.min_correlation and overlap >= need:
                    return homography, inliers, True, cc, False
            h, cc, overlap = register_binned(a, b, initial[p], self.factor)
            if cc >= self.min_correlation and overlap >= need:
                return h, max(8, int(round(100 * cc ** 2))), True, cc, True
            return homography, inliers, False, cc, False

        checked = executor.map(check, range(len(pairs)))
        if not checked:
            return found
        ok = np.array([c[2] for c in checked], bool)
        rescued = np.array([c[4] for c in checked], bool)
        stats = self._stats
        stats["checked"] += int(found.ok.sum())
        stats["rejected_by_check"] += int((found.ok & ~(ok & ~rescued)).sum())
        stats["rescued"] += int(rescued.sum())
        stats["correlations"].extend(c[3] for c in checked)
        return PairRegistrations(np.stack([c[0] for c in checked]), found.matches,
                                 np.array([c[1] for c in checked], found.inliers.dtype), ok)

    def take_statistics(self) -> dict[str, Any]:
        """Return the check's figures since the last call (JSON-ready) and reset them.

        Returns:
            ``{"binning", "checked", "rejected_by_check", "rescued",
            "median_correlation", "min_correlation"}`` (correlations of the pairs'
            final homographies on binned frames; -1 where ECC failed).
        """
        stats, self._stats = self._stats, self._empty()
        cc = np.asarray(stats.pop("correlations"), np.float64)
        return {"binning": self.factor, **stats,
                "median_correlation": float(np.median(cc)) if len(cc) else None,
                "min_correlation": float(cc.min()) if len(cc) else None}
