"""Per-frame uncertainty of the trajectory, from registrations held out of the fit.

A confidence report built from the fit's own residuals agrees with a wrong trajectory:
at the mosaic levels every merged frame is registered against a panorama made from the
same estimate, so a segment that is wrong consistently is also consistent with its
panorama. The last level therefore also registers its *consecutive merged frames directly
against each other* (:attr:`~photonpano.records.LocateResult.crosscheck`), registrations
that no keyframe used. Where the trajectory is right, each such registration agrees with
the final homographies up to registration noise; where it is wrong, it disagrees by the
error's change between the two groups, or fails. This is the "held-out data" test of
model validation (cross-validation of a fit by measurements it did not see; Hastie,
Tibshirani and Friedman, *The Elements of Statistical Learning*, Sec. 7.10).

From the held-out residuals and the level loop's own history :func:`frame_uncertainty`
predicts a 1-sigma error for every binary frame from these terms, added in quadrature, and a floor:

- *local*: the root mean square of the held-out residuals near the frame, times
  :data:`RESIDUAL_TO_SIGMA`;
- *chain drift*: a residual sees only the *difference* of two neighbouring groups'
  errors, so the part of the error that neighbours share, a slow drift of level 1's chain
  of registrations (which the mosaic levels keep: their template is made from the same
  chain), does not show in it. It grows with how far the camera travelled from the middle
  frame (the panorama's reference), per frame extent travelled (the frame's width or
  height along the displacement): :data:`CHAIN_DRIFT_PER_FRAME_EXTENT` times level 1's
  pose-graph residual. A fast pan across three frame widths drifted by 1-2 px at its ends
  while its local residuals predicted 0.4 px.
- *jump*: where one held-out pair disagrees by more than :data:`LIMIT_PX`, one of its two
  groups is off by at least half of that, so the frames between them get at least that
  sigma (the local RMS, at :data:`RESIDUAL_TO_SIGMA`, dilutes a single 6 px disagreement
  among its neighbours to 0.44 px);
- *shape*: the error that grows slowly along the capture (a shear or keystone ramp), which
  changes by less than the consecutive pairs' noise between neighbours and which the
  mosaic template holds too, from held-out chains of registrations of merged frames far
  apart (:func:`~photonpano.long_pairs.chain_shape_error`: the links' disagreements with
  the final trajectory summed along each chain, less twice the standard error the chains'
  spread gives), at face value (a 50-degree tripod pan over the city, 0.31 px: median
  sigma 0.087 -> 0.23 px, its frames within 2 sigma 28 -> 72 %; a facade crossed by a
  disc, 0.14 px: 52 -> 84 % within 2 sigma), and, in quadrature, what the chains cannot
  resolve, their standard error, where the capture's frames travel far from the middle
  frame: none where every frame overlaps it by half (:data:`UNRESOLVED_SHAPE_EXTENTS`),
  all of it where the farthest no longer overlaps it. Frames that overlap the middle one
  share the template with it; a frame a whole frame away is tied to it only through the
  frames in between, and after the global alignment the shape error that builds up so is
  spread over every frame. Fast pans had it under-predicted: at 0.12 px/frame over 31
  photographs, 67 -> 94 % of the ``ok`` captures' frames within 2 sigma, and the evaluation
  suite's 96.2 -> 97.7 %;
- *level change*: how far the mosaic levels moved each frame, from the first mosaic
  level's trajectory to the last's, times :data:`LEVEL_CHANGE_TO_SIGMA` (with the default
  three levels, the move of level 3), measured both in the panorama's frame and after the
  best global alignment of the two trajectories (:func:`level_change`): a move that all
  frames share relative to the middle frame is invisible at the middle frame in the first
  and spread over every frame in the second, as in the trajectory error. A level that
  still moves the trajectory by a pixel has not converged, and one whose merged frames
  hold too few photons to register moves it by its noise; in both cases the error that is
  left is of the order of that move (the a-posteriori error estimate of a fixed-point
  iteration, e.g. Quarteroni, Sacco and Saleri, *Numerical Mathematics*, Sec. 6.5: the
  distance to the limit is at most ``r / (1 - r)`` times the last step, r the
  contraction). Where the iteration converges slowly (r near 1) the last step alone
  shrinks with every level added while the error hardly does, which is why the move since
  the first mosaic level is taken (the suite's dark outdoor scene with ``levels: 4``: 0.86
  px, the last step predicted 0.23 px and said ``ok``). The first mosaic level itself is
  not compared with the pairwise level 1: it moves the frames by level 1's error, which it
  has just removed (with ``levels: 2`` this term is left out); nor, for the same reason,
  are the frames level 1 extrapolated, before its first reference frame and after its
  last: they get the move at those frames (the suite's dark outdoor scene, 0.309 px, moved
  its first 64 frames by over 0.83 px, 0.54-0.58 px off, and said ``degraded``). Neither
  the held-out pairs (smooth, shared errors) nor the chain residual (level 1's own
  consistency) see this error: a dark scene at 0.9 px predicted 0.41 px from them, a
  low-texture interior at 0.59 px 0.28 px.

The constants were set on the evaluation suite (``benchmarks/suite.py``: 48 captures of
its 16 photographs, paths, light levels and nuisances) and checked on eight photographs
outside it (docs/accuracy.md): the share of frames of ``ok`` captures whose actual error
is within twice their predicted sigma, each capture's median sigma over its RMSE, and
which captures end ``degraded``; where the runs' noise leaves a choice, the larger sigma
is the safer error. How each constant came about: docs/accuracy.md, "How the predicted
sigma was calibrated". Frames whose trajectory rests on
registrations that failed (bridged from neighbours) or on no registration at all (before
the first or after the last group's reference frame by more than half a group) are marked
*unverified*.

Where the last level registers pairs itself (the ``pairwise`` scheme, whose pose graph
holds redundant pairs), its consecutive pairs' residuals against the solved keyframes
serve as the evidence instead (not held out: a weaker test; ``evidence`` says which).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .long_pairs import chain_shape_error
from .metrics import trajectory_error
from .records import LevelResult

__all__ = ["FrameUncertainty", "frame_uncertainty", "held_out_residuals", "frame_extents_travelled", "level_change",
           "RESIDUAL_TO_SIGMA", "CHAIN_DRIFT_PER_FRAME_EXTENT", "LEVEL_CHANGE_TO_SIGMA", "UNRESOLVED_SHAPE_EXTENTS",
           "NEIGHBOURS", "LIMIT_PX"]

RESIDUAL_TO_SIGMA = 0.3
"""Local term of the predicted per-frame sigma over the local RMS of held-out pair
residuals (calibrated on the evaluation suite, see the module)."""

CHAIN_DRIFT_PER_FRAME_EXTENT = 0.2
"""Chain-drift term of the predicted sigma per frame extent travelled from the middle
frame, in units of level 1's pose-graph residual
(``levels[0].quality.pose_graph_residual_px``; calibrated on the evaluation suite)."""

LEVEL_CHANGE_TO_SIGMA = 1.2
"""Level-change term of the predicted sigma over each frame's mean corner distance
between the last level's trajectory and the first mosaic level's (calibrated on the
evaluation suite)."""

UNRESOLVED_SHAPE_EXTENTS = 0.5
"""Frame extents the capture's farthest frame travels from the middle frame before the shape term
takes in the held-out chains' standard error: none up to this, all of it from twice this, in
proportion between (see the module)."""

NEIGHBOURS = 8
"""Residuals on each side of a pair that enter its local RMS."""

LIMIT_PX = 1.0
"""A frame whose predicted sigma exceeds this many pixels makes the run ``degraded``."""


@dataclass(frozen=True)
class FrameUncertainty:
    """Predicted trajectory error of every binary frame.

    Attributes:
        sigma_px: (T,) float64 predicted 1-sigma error of each frame's corner positions
            in panorama pixels (mean distance of the four corners from where they belong,
            as :func:`~photonpano.metrics.trajectory_error` measures it). ``inf`` where
            no evidence exists at all.
        unverified: (T,) bool frames whose trajectory rests on a failed (bridged)
            registration or on extrapolation beyond the registered groups.
        evidence: ``"held-out pairs"`` (the last level's cross-check) or ``"pose graph"``
            (a pairwise last level's own pairs).
        pairs: registrations used as evidence.
        failed: of them, how many failed.
        shape_links: registrations of the held-out chains behind the shape term (0: none).
        shape_px: (T,) float64 the shape term of each frame in pixels
            (:mod:`photonpano.long_pairs`), or None without it.
    """

    sigma_px: NDArray[np.float64]
    unverified: NDArray[np.bool_]
    evidence: str
    pairs: int
    failed: int
    shape_links: int = 0
    shape_px: NDArray[np.float64] | None = None

    def summary(self, frame_rate_hz: float, limit_px: float = LIMIT_PX) -> dict[str, Any]:
        """The ``run.json`` entry: ``median_px``, ``p95_px``, ``max_px``, the frame ranges above ``limit_px``.

        Args:
            frame_rate_hz: binary frames per second (for the ranges' times in seconds).
            limit_px: sigma above which a frame range is listed, in pixels.

        Returns:
            ``{"evidence", "pairs", "failed_pairs", "shape_links", "shape_max_px", "median_px", "p95_px", "max_px",
            "limit_px", "above_limit", "unverified"}``; the last two are lists of
            ``{"frames": [first, last], "seconds": [t0, t1], "max_px"}`` (frames 0-based,
            inclusive; ``max_px`` None where infinite).
        """
        finite = np.where(np.isfinite(self.sigma_px), self.sigma_px, np.nan)
        return {
            "evidence": self.evidence, "pairs": self.pairs, "failed_pairs": self.failed,
            "shape_links": self.shape_links,
            "shape_max_px": None if self.shape_px is None else _number(np.max(self.shape_px)),
            "median_px": _number(np.nanmedian(finite)), "p95_px": _number(np.nanpercentile(finite, 95)),
            "max_px": _number(np.max(self.sigma_px)), "limit_px": limit_px,
            "above_limit": _ranges(~(self.sigma_px <= limit_px), self.sigma_px, frame_rate_hz),
            "unverified": _ranges(self.unverified, self.sigma_px, frame_rate_hz),
        }


def frame_uncertainty(result: LevelResult, width: int, height: int, chain_residual_px: float | None = None,
                      previous: NDArray[np.float64] | None = None,
                      level_one_span: tuple[int, int] | None = None) -> FrameUncertainty | None:
    """Predict every frame's trajectory error from the last level's held-out evidence.

    Args:
        result: the last level's :class:`~photonpano.records.LevelResult` (its
            ``homographies`` are the run's final frame-to-panorama homographies).
        width: frame width in pixels.
        height: frame height in pixels.
        chain_residual_px: level 1's pose-graph residual in pixels (median mean-corner
            distance of its pairs from the solved keyframes,
            :func:`~photonpano.quality.level_figures`), or None (no chain term).
        previous: (T, 3, 3) float64 frame-to-panorama homographies (same panorama) of
            the first level after level 1 of the last level's scheme (the pipeline passes
            the first mosaic level's, level 2 by default), or None (no level-change term:
            no such level before the last).
        level_one_span: ``(first, last)`` 0-based frame indices of level 1's first and last
            reference frame (clipped to the capture), or None: the frames outside get the
            level-change term at those frames (see the module).

    Returns:
        The :class:`FrameUncertainty`, or None if the level holds no evidence (a mosaic
        level run without the cross-check, or a single group).

    Raises:
        ValueError: if ``previous`` does not hold one homography per frame.
    """
    evidence = held_out_residuals(result, width, height)
    if evidence is None:
        return None
    index, middle, residual, ok, kind = evidence
    n = len(result.homographies)
    if previous is not None and previous.shape != result.homographies.shape:
        raise ValueError(f"previous level's homographies {previous.shape} do not match the last level's "
                         f"{result.homographies.shape}")
    sigma_pairs = RESIDUAL_TO_SIGMA * _local_rms(np.where(ok, residual, np.nan), NEIGHBOURS)
    known = np.isfinite(sigma_pairs)
    if known.any():
        local = np.interp(np.arange(n, dtype=np.float64), middle[known], sigma_pairs[known])
        travelled = frame_extents_travelled(result.homographies, width, height)
        drift = CHAIN_DRIFT_PER_FRAME_EXTENT * (chain_residual_px or 0.0) * travelled
        # how far the levels moved the frames; the shape drift's correction is not a level's step
        # (its evidence, the chains, gives the shape term)
        moved = result.homographies if result.uncorrected is None else result.uncorrected
        change = (LEVEL_CHANGE_TO_SIGMA * level_change(moved, previous, width, height)
                  if previous is not None else np.zeros(n))
        if level_one_span is not None:  # level 1 extrapolated beyond it; its error is what moved there
            first, last = (int(np.clip(f, 0, n - 1)) for f in level_one_span)
            change[:first], change[last + 1:] = change[first], change[last]
        shape = _shape_term(result, travelled, width, height)
        sigma = np.sqrt(local ** 2 + drift ** 2 + change ** 2 + (0.0 if shape is None else shape) ** 2)
    else:
        sigma, shape = np.full(n, np.inf), None
    reference = result.groups.reference
    # a held-out pair off by more than the limit: one of its two groups is off by at least half of it
    for (a, b), off in zip(index[ok], residual[ok]):
        if off > LIMIT_PX:
            sigma[reference[a]:reference[b] + 1] = np.maximum(sigma[reference[a]:reference[b] + 1], off / 2)
    unverified = np.zeros(n, bool)
    for a, b in index[~ok]:
        unverified[reference[a]:reference[b] + 1] = True
    # extrapolated: frames beyond the registered groups' span by more than half a group
    groups = result.groups
    half = int(np.median(groups.stop - groups.start)) // 2
    unverified[:max(0, int(reference.min()) - half)] = True
    unverified[int(reference.max()) + half + 1:] = True
    # a failed registration leaves its stretch with no measure of error: at least the limit
    sigma[unverified] = np.maximum(sigma[unverified], 2 * LIMIT_PX)
    located = result.located
    return FrameUncertainty(sigma, unverified, kind, int(len(ok)), int((~ok).sum()),
                            0 if located.chain is None else len(located.chain.ok), shape)


def _shape_term(result: LevelResult, travelled: NDArray[np.float64], width: int, height: int
                ) -> NDArray[np.float64] | None:
    """(T,) float64 the shape term of each frame (see the module), or None without the chains.

    ``travelled`` is (T,) float64 :func:`frame_extents_travelled` of the final homographies (frame extents).
    """
    located = result.located
    if located.chain is None or located.chain_index is None:
        return None
    found = chain_shape_error(located.chain.homographies, located.chain.ok, located.chain_index,
                              result.groups.reference, result.homographies, width, height)
    if found is None:
        return None
    shape, unresolved = found
    return np.hypot(shape, unresolved * np.clip(travelled.max() / UNRESOLVED_SHAPE_EXTENTS - 1.0, 0.0, 1.0))


def level_change(homographies: NDArray[np.float64], previous: NDArray[np.float64],
                 width: int, height: int) -> NDArray[np.float64]:
    """How far the mosaic levels moved each frame, in the panorama's frame and in none.

    The panorama's frame is the middle frame's, so a move that every frame shares
    relative to it (a slowly converging error of the trajectory's shape) shows at every
    frame but the middle one, and the trajectory error (measured after the best global
    alignment, :func:`~photonpano.metrics.trajectory_error`) is spread over all of them
    instead. Both are measured; each frame gets the larger.

    Args:
        homographies: (T, 3, 3) float64 frame-to-panorama homographies of the last level.
        previous: (T, 3, 3) float64 the same of an earlier level, same panorama.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (T,) float64 per-frame mean corner distance in panorama pixels: the larger of the
        distance as it stands and after the least-squares homography that aligns
        ``homographies`` with ``previous`` (fitted on 5 000 evenly spaced frames).

    Raises:
        ValueError: if the two stacks differ in shape.
    """
    if homographies.shape != previous.shape:
        raise ValueError(f"level_change: homographies {homographies.shape} and previous {previous.shape} differ")
    # the fit on every frame's corners takes 0.5 s at 100 000 frames; on 5 000 it is the same to 1e-5 px
    fit = np.linspace(0, len(homographies) - 1, min(len(homographies), 5000)).round().astype(int)
    alignment = trajectory_error(homographies[fit], previous[fit], width, height).alignment
    aligned = geometry.mean_corner_distance(alignment @ homographies, previous, width, height)
    return np.maximum(geometry.mean_corner_distance(homographies, previous, width, height), aligned)


def frame_extents_travelled(homographies: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    """How far each frame's centre lies from the middle frame's, in frame extents.

    Args:
        homographies: (T, 3, 3) float64 frame-to-panorama homographies (panorama: the
            middle frame's pixels).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (T,) float64 distance of each frame centre from the middle frame's centre, over the
        frame's extent along that direction (``|ux| width + |uy| height`` for the unit
        direction u): 1 where the frames just stop overlapping side by side.
    """
    centre = np.array([width / 2.0, height / 2.0, 1.0])
    mapped = homographies @ centre
    offset = mapped[:, :2] / mapped[:, 2:] - (homographies[len(homographies) // 2] @ centre)[:2]
    return geometry.extents_apart(offset, width, height)


Evidence = tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], str]
"""``(index, middle, residual, ok, evidence)`` of :func:`held_out_residuals`."""


def held_out_residuals(result: LevelResult, width: int, height: int) -> Evidence | None:
    """The last level's evidence pairs and how far each disagrees with the final homographies.

    Args:
        result: the last level's :class:`~photonpano.records.LevelResult`.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``(index, middle, residual, ok, evidence)``: (P, 2) int group indices of each pair;
        (P,) float64 frame midway between the pair's reference frames; (P,) float64 mean
        corner distance in pixels between the pair's registration and the homography the
        final trajectory implies between them; (P,) bool registrations that succeeded with a
        finite residual; ``"held-out pairs"`` or ``"pose graph"`` (see the module). None if
        the level holds no evidence.
    """
    located, homographies = result.located, result.homographies
    if located.crosscheck is not None and located.crosscheck_index is not None:
        index, regs, evidence = located.crosscheck_index, located.crosscheck, "held-out pairs"
    elif located.pair_index is not None:
        consecutive = located.primary
        index, regs, evidence = located.pair_index[consecutive], located.registrations.take(consecutive), "pose graph"
    else:
        return None
    if not len(index):
        return None
    reference = result.groups.reference
    expected = geometry.invert(homographies[reference[index[:, 0]]]) @ homographies[reference[index[:, 1]]]
    residual = geometry.mean_corner_distance(regs.homographies, expected, width, height)
    ok = regs.ok & np.isfinite(residual)
    # a pair's evidence describes the frames between its two reference frames
    middle = (reference[index[:, 0]] + reference[index[:, 1]]) / 2.0
    return index, middle, residual, ok, evidence


def _local_rms(values: NDArray[np.float64], neighbours: int) -> NDArray[np.float64]:
    """RMS of the finite ``values`` within ``neighbours`` places on each side (NaN where none)."""
    finite = np.isfinite(values)
    squares = np.concatenate([[0.0], np.cumsum(np.where(finite, values, 0.0) ** 2)])
    counts = np.concatenate([[0], np.cumsum(finite)])
    i = np.arange(len(values))
    lo, hi = np.maximum(i - neighbours, 0), np.minimum(i + neighbours + 1, len(values))
    count = counts[hi] - counts[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.sqrt((squares[hi] - squares[lo]) / np.maximum(count, 1)), np.nan)


def _ranges(mask: NDArray[np.bool_], sigma: NDArray[np.float64], frame_rate_hz: float) -> list[dict[str, Any]]:
    """The runs of True in ``mask`` as ``{"frames", "seconds", "max_px"}`` entries."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    out = []
    for start, stop in zip(edges[::2], edges[1::2]):
        out.append({"frames": [int(start), int(stop - 1)],
                    "seconds": [round(float(start) / frame_rate_hz, 6), round(float(stop - 1) / frame_rate_hz, 6)],
                    "max_px": _number(sigma[start:stop].max())})
    return out


def _number(value: float) -> float | None:
    """A JSON-ready float: None for NaN or infinity."""
    value = float(value)
    return value if np.isfinite(value) else None
