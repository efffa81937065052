"""A confidence report that needs no ground truth: per-level figures, ``status`` and ``warnings``.

A run must never end with a confident wrong answer. Each level records figures that
any capture has (:func:`level_figures`): photons per pixel per group, the share of
registrations that failed and were bridged, and how well the registered pairs agree
with the solved keyframes (pose-graph residual) or how far the panorama moved each
merged frame (levels against the mosaic). At the end, a sample of groups is merged
with the final homographies and compared with the panorama rendered at their pose
(:func:`panorama_agreement`): a merged frame shows the scene it was registered to only
if the trajectory is right. :func:`assess` turns the figures into ``status``
(``"ok"`` or ``"degraded"``) and one-line warnings (``docs/outputs.md``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .budget.probe import GroupPlan
from .imaging import binned_frame, normalised_correlation
from .stages import Groups, MergedFrames
from .watchdog import watched

__all__ = ["level_figures", "panorama_agreement", "assess", "movers_record", "THRESHOLDS"]

THRESHOLDS = {"failed_fraction": 0.2, "failed_against_panorama": 0.1, "rejected_fraction": 0.1,
              "residual_px": 2.0, "agreement": 0.5, "photons_per_pixel": 2.0}
"""Limits of :func:`assess`: bridged registrations (fraction; of pairs at the last
level, 0.5 at earlier ones, whose errors the later levels correct; of registrations
against the panorama at any level), replaced keyframes
(fraction), median pose-graph residual (pixels), median agreement of merged frames
with the panorama (correlation), detections per (binned) pixel in a merged frame."""


def level_figures(result, plan: GroupPlan, width: int, height: int) -> dict[str, Any]:
    """Ground-truth-free figures of one finished level.

    Args:
        result: the :class:`~photonpano.records.LevelResult`.
        plan: the capture's :class:`~photonpano.budget.probe.GroupPlan`.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``{"photons_per_pixel_per_group"`` (None for intensity sources),
        ``"failed_fraction"`` (primary registrations bridged), ``"pose_graph_residual_px"``
        (median mean-corner distance between each successful pair's homography and
        the solved keyframes; pairwise levels) or ``"median_correction_px"`` (median
        corner shift of the registrations against the panorama), ``"rejected_fraction"``}.
    """
    located = result.located
    pairs, index, primary = located.registrations, located.pair_index, located.primary
    p = plan.probe.photons_per_pixel_per_frame if plan.probe is not None else None
    length = float(np.median(result.groups.stop - result.groups.start))
    out: dict[str, Any] = {
        "photons_per_pixel_per_group": p * length if p is not None else None,
        "failed_fraction": float((~pairs.ok[primary]).mean()) if primary.any() else 0.0,
        "rejected_fraction": result.rejected_keyframes / max(len(result.groups), 1),
    }
    ok = pairs.ok
    if index is None:
        moved = geometry.mean_corner_distance(pairs.homographies[ok], np.eye(3)[None], width, height)
        out["median_correction_px"] = float(np.median(moved)) if len(moved) else None
    elif ok.any():
        k = located.keyframes
        solved = np.linalg.inv(k[index[ok, 0]]) @ k[index[ok, 1]]
        out["pose_graph_residual_px"] = float(np.median(geometry.mean_corner_distance(pairs.homographies[ok], solved,
                                                                         width, height)))
    return out


def panorama_agreement(source, merger, homographies: NDArray[np.float64], panorama, group_size: int,
                       factor: int, *, samples: int = 12) -> dict[str, Any]:
    """Compare merged frames with the panorama rendered at their pose.

    ``samples`` groups of ``group_size`` frames spread over the capture are merged with
    the final homographies, the panorama is resampled into each reference frame's grid
    (:func:`~photonpano.views.panorama_views`), and both are binned by ``factor``
    (square-root flux, see :func:`~photonpano.imaging.binned_frame`) and correlated.

    Args:
        source: the capture.
        merger: the built merger.
        homographies: (T, 3, 3) float64 final frame-to-panorama homographies.
        panorama: the final :class:`~photonpano.records.Panorama`.
        group_size: frames per sampled group.
        factor: binning of the comparison (pixels per side).
        samples: groups compared.

    Returns:
        ``{"median", "min", "binning"}``: correlations (1 = identical up to gain and
        offset, about 0 for photon noise).
    """
    from .views import panorama_views

    n = source.n_frames
    m = min(group_size, n)
    refs = np.unique(np.linspace(m // 2, n - 1 - (m - 1) // 2, samples).astype(np.int64))
    start = np.clip(refs - m // 2, 0, n - m)
    groups = Groups(start=start, stop=start + m, reference=refs)
    with watched("merger", merger, "merge"):  # one group at a time: a window would count the frames between them
        merged = MergedFrames.concat(*(merger.merge(source, homographies, groups.select(np.array([i])))
                                       for i in range(len(groups))))
    views = panorama_views(panorama, panorama.homographies[refs], source.height, source.width, min_frames=m)
    values = []
    for i in range(len(refs)):
        a = binned_frame(merged.flux[i], merged.masks[i], factor)
        b = binned_frame(views.flux[i], views.masks[i], factor)
        values.append(normalised_correlation(a[0], b[0], a[1] & b[1]))
    return {"median": float(np.median(values)), "min": float(np.min(values)), "binning": factor}


def assess(plan: GroupPlan, levels: list[dict[str, Any]],
           agreement: dict[str, Any] | None, uncertainty: dict[str, Any] | None = None) -> tuple[str, list[str]]:
    """Decide ``status`` and the warnings of a run from its figures.

    Args:
        plan: the group-size plan (its probe's findings are checked too, and its
            ``flicker``: flicker over part of the field is warned about unless the groups
            span whole periods (:func:`~photonpano.budget.probe.whole_flicker_periods`): it
            biases every registration alike, which no held-out pair can see (measured on
            simulated half-lit captures: 0.4-5 px where steady light gives 0.1 px).
        levels: per-level statistics rows, each with a ``"quality"`` entry from
            :func:`level_figures` (and ``"registration_check"`` where the binned check ran).
        agreement: :func:`panorama_agreement`'s result, or None if it was not measured.
        uncertainty: the per-frame uncertainty's summary
            (:meth:`~photonpano.uncertainty.FrameUncertainty.summary`), or None: frame
            ranges whose predicted error exceeds its limit, or that rest on failed or
            extrapolated registrations, are warned about by frames and seconds.

    Returns:
        ``(status, warnings)``: ``"ok"`` when no warning was raised, else ``"degraded"``;
        one line per problem.
    """
    t = THRESHOLDS
    warnings: list[str] = []
    probe = plan.probe
    if probe is not None and probe.photons_per_pixel_per_frame is not None and probe.speed_px_per_frame is None:
        warnings.append("the motion pre-pass found no scene structure in the photons (median correlation "
                        f"{np.median(probe.correlations):.2f} of blocks {probe.block_frames} frames apart)")
    per_group = plan.photons_per_pixel_per_group
    if per_group is not None and per_group * plan.binning ** 2 < t["photons_per_pixel"]:
        warnings.append(f"only {per_group * plan.binning ** 2:.1f} photons per (binned) pixel per group "
                        "at level 1")
    for row in levels:
        q, k = row.get("quality", {}), row["level"]
        # a pairwise level's failures are corrected by the later levels (only many matter
        # there); a registration against a good panorama rarely fails
        limit = t["failed_fraction"] if row is levels[-1] else max(t["failed_fraction"], 0.5)
        if "median_correction_px" in q:
            limit = t["failed_against_panorama"]
        if q.get("failed_fraction", 0) > limit:
            warnings.append(f"level {k}: {q['failed_fraction']:.0%} of the registrations failed "
                            "and were bridged")
        if q.get("rejected_fraction", 0) > t["rejected_fraction"]:
            warnings.append(f"level {k}: {q['rejected_fraction']:.0%} of the keyframe updates "
                            "were implausible")
        if (q.get("pose_graph_residual_px") or 0) > t["residual_px"]:
            warnings.append(f"level {k}: registered pairs disagree with the solved trajectory by "
                            f"{q['pose_graph_residual_px']:.1f} px (median)")
    if uncertainty is not None:
        warnings.extend(_uncertainty_warnings(uncertainty))
    flicker = plan.flicker
    if flicker is not None and flicker.partial and not flicker.spans_whole_periods(plan.group_size):
        regions = ", ".join(flicker.record()["regions"])
        warnings.append(f"light flickering at {flicker.frequency_hz:.4g} Hz over part of the scene "
                        f"({regions} of the frame; depth up to {flicker.depth.max():.2f}): "
                        "brightness changes between virtual exposures bias the registrations")
    if agreement is not None and not agreement["median"] >= t["agreement"]:
        warnings.append(f"merged frames agree poorly with the panorama at their pose (median correlation "
                        f"{agreement['median']:.2f} < {t['agreement']})")
    return ("degraded" if warnings else "ok"), warnings


def _uncertainty_warnings(summary: dict[str, Any], listed: int = 4) -> list[str]:
    """One line per frame range that is unverified or predicted above the limit (at most ``listed`` each)."""
    def span(entry: dict[str, Any]) -> str:
        (a, b), (s0, s1) = entry["frames"], entry["seconds"]
        return f"frames {a}-{b} ({s0:.4g}-{s1:.4g} s)"

    def worst(entry: dict[str, Any]) -> str:
        return "unknown" if entry["max_px"] is None else f"{entry['max_px']:.2g} px"

    lines = []
    unverified = summary["unverified"]
    if unverified:
        lines.append("the trajectory rests on failed (bridged) or extrapolated registrations at "
                     + ", ".join(span(e) for e in unverified[:listed])
                     + (f" and {len(unverified) - listed} more ranges" if len(unverified) > listed else ""))
    above = summary["above_limit"]
    if above:
        worst_first = sorted(above, key=lambda e: -(e["max_px"] if e["max_px"] is not None else np.inf))
        lines.append(f"held-out registrations predict errors above {summary['limit_px']:g} px at "
                     + ", ".join(f"{span(e)}: up to {worst(e)}" for e in worst_first[:listed])
                     + (f" and {len(above) - listed} more ranges" if len(above) > listed else ""))
    return lines


def movers_record(stats: list[dict[str, Any]]) -> dict[str, Any] | None:
    """``run.json``'s ``movers``: the level whose mosaic template decided on mover rejection, and what it found.

    ``{"level", "engaged", "template_fraction", "largest_region"}`` from the first level row with a
    ``movers`` entry (:attr:`~photonpano.records.LocateResult.movers`); None where no
    level rejects movers (``mosaic.reject_movers: null``, or no mosaic level).
    """
    for row in stats:
        if row.get("movers") is not None:
            return {"level": row["level"], **{key: row["movers"][key] for key in
                                              ("engaged", "template_fraction", "largest_region")}}
    return None
