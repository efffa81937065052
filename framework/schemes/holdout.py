"""A leave-one-out template for the mosaic levels (spec ``mosaic.holdout``).

A template made from every photon holds each merged frame's own photons, and those of its
neighbours in time, placed with the errors of the estimate being corrected: the
registration is pulled toward that estimate, and where the canvas is seen by those frames
alone (the new strip at the end of a pan) it can only agree with it. With ``holdout``
(spec ``mosaic.holdout``, off by default) the capture is cut into that many runs of
consecutive frames and each group is registered against the panorama of the runs its
frames do not fall in, a leave-one-out (jackknife) template made from the runs' sums at no
extra pass (:class:`HoldoutTemplate`). Measured on the evaluation suite (2026-11-25), 4
runs: the bundled office's pan, which ends on a strip of corridor only its last frames
see, 0.124 -> 0.033 px, dandelions 0.051 -> 0.040, coffee 0.052 -> 0.044; but the
unbiased registrations are noisier than the ones pulled toward the estimate, and most
captures lost (the room 0.023 -> 0.046 px, Hubble 0.047 -> 0.064, the sunset's zigzag at
flux 0.05 0.138 -> 0.296, the room's fast pan 0.54 -> 2.46); 8 and 16 runs, the leave-out
at the first mosaic level only, and untrusting only the template pixels the group's own
runs dominate did not remove the losses.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..compose import BilinearCompositor
from ..records import MergedFrames, Panorama
from ..views import panorama_views

__all__ = ["HoldoutTemplate"]


class HoldoutTemplate:
    """A leave-one-out template: the panorama of every run of frames but those a group falls in.

    The capture's frames are cut into E runs of consecutive frames (the compositor's
    virtual exposures, :func:`~photonpano.robust_merge.exposure_bounds`), each summed on
    the canvas apart; the template of a group of frames ``[start, stop)`` is the flux MLE
    (paper Eq. 3) of the sums of the other runs, so neither its own photons nor those of
    the neighbours sharing its pose error are in what it is registered against (the
    jackknife: Quenouille 1956; Efron and Tibshirani, "An Introduction to the Bootstrap",
    1993, Ch. 11). A group whose frames touch every run is registered against them all.

    Args:
        compositor: a :class:`~photonpano.compose.BilinearCompositor` with ``exposures``
            >= 2, fed with every frame (by :func:`~photonpano.compose.compose`).
        source: the capture it was fed from.

    Attributes:
        homographies: (T, 3, 3) float64 frame-to-canvas homographies (as a :class:`Panorama`'s).
        bounds: (E + 1,) int64 first frame of each run, then the frame count T.
    """

    def __init__(self, compositor: BilinearCompositor, source: Any) -> None:
        """Take the runs' sums from a fed compositor."""
        counts, frames, self.homographies = compositor.exposure_sums()
        self.bounds = compositor.bounds
        self._counts, self._frames = counts, frames
        self._source = source
        self._panoramas: dict[tuple[int, ...], Panorama] = {}

    def runs_of(self, start: int, stop: int) -> tuple[int, ...]:
        """The runs that frames ``[start, stop)`` fall in (all of them: none left out)."""
        runs = tuple(np.flatnonzero((self.bounds[:-1] < stop) & (self.bounds[1:] > start)).tolist())
        return () if len(runs) == len(self.bounds) - 1 else runs

    def panorama(self, start: int, stop: int) -> Panorama:
        """The :class:`Panorama` of the runs frames ``[start, stop)`` do not fall in (flux in photons/s, NaN unseen)."""
        runs = self.runs_of(start, stop)
        if runs not in self._panoramas:
            from ..intensity import estimate_radiance

            keep = np.ones(len(self._counts), bool)
            keep[list(runs)] = False
            frames = self._frames[keep].sum(axis=0)
            flux = estimate_radiance(self._source, self._counts[keep].sum(axis=0), frames)
            self._panoramas[runs] = Panorama(flux=flux, frames=frames, homographies=self.homographies)
        return self._panoramas[runs]

    def prepare(self, starts: NDArray[np.int64], stops: NDArray[np.int64]) -> None:
        """Make the templates of groups ``[starts[i], stops[i])`` (before threads read them)."""
        for start, stop in zip(starts, stops):
            self.panorama(int(start), int(stop))

    def views(self, starts: NDArray[np.int64], stops: NDArray[np.int64], to_canvas: NDArray[np.float64],
              height: int, width: int, min_frames: float, exposure_s: float | None) -> MergedFrames:
        """Each group's template resampled into its reference frame's grid (see :func:`panorama_views`).

        Args:
            starts: (G,) int64 first frame of each group.
            stops: (G,) int64 frame after each group's last.
            to_canvas: (G, 3, 3) float64 reference-frame-to-canvas homographies.
            height: frame height in pixels.
            width: frame width in pixels.
            min_frames: canvas pixels observed by fewer binary frames are not trusted.
            exposure_s: the views' ``exposure_s``.

        Returns:
            G :class:`MergedFrames`, in the groups' order.
        """
        return MergedFrames.concat(*(
            panorama_views(self.panorama(int(start), int(stop)), h[None], height, width, min_frames, exposure_s)
            for start, stop, h in zip(starts, stops, to_canvas)))
