"""Moving objects in binned frames: the brightest compact blob, and a probe's shift without it.

A lit object crossing a darker scene can carry most of a binned frame's contrast, so that a
correlation, phase correlation or ECC of two frames follows the object, not the scene. Two
steps guard against it: the level-1 pair check (:class:`~photonpano.schemes.check.PairCheck`,
``mover_guard``) and the speed probe (:func:`~photonpano.budget.probe.probe_capture`) register
the frames again without each one's :func:`brightest_blob` (``docs/real_scenes.md``, "Moving
objects"). A mosaic level's robust template finds a mover by the regions it left out
(:func:`moving_fraction`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .imaging import register_binned

if TYPE_CHECKING:
    from .records import Panorama

__all__ = ["brightest_blob", "moving_fraction", "shift_without_mover", "MOVER_DISAGREEMENT_PX", "MOVER_MIN_CORRELATION"]


def brightest_blob(image: NDArray[np.float32], valid: NDArray[np.bool_], *,
                   levels: tuple[float, ...] = (0.25, 0.5, 0.75), margin: int = 3, grow: int = 6,
                   max_fraction: float = 0.25, min_solidity: float = 0.5, min_share: float = 0.9
                   ) -> NDArray[np.bool_]:
    """The bright compact region that carries most of a binned frame's contrast, if there is one.

    A single bright, compact region (a lit object crossing a dark scene) can carry most of
    a binned frame's contrast, so a correlation, phase correlation or ECC of two frames
    then follows that region's motion, which is the scene's only if the region is static.
    The pair check registers and checks the frames again without it
    (:class:`~photonpano.schemes.check.PairCheck`).

    On a bright, textured scene the object touches the scene's own bright texture (a lit
    disc on a brick facade's mortar lines, half as bright as it): above the first level
    they form one web, neither small nor compact. The higher ``levels`` then cut the
    object's core out of the web; such a core counts only where it holds at least
    ``min_share`` of the contrast energy above its level (a static scene's brightest
    patch of texture has rivals there, the object none), and it is grown back into the
    pixels above the first level within ``grow`` pixels (its motion-blurred ends). On the
    brick facade crossed by a disc of radius 30 px (level 1's merged frames, 2026-11-26)
    the first level found the disc in 7 of the 27 frames that show it, the three levels
    in all 27, and in none of the 63 frames of the static capture.

    Args:
        image: (h, w) float32 binned frame (:func:`~photonpano.imaging.binned_frame`).
        valid: (h, w) bool its valid pixels.
        levels: increasing fractions (each in (0, 1)); at each in turn the candidate
            regions are where the image exceeds its median by that fraction of the
            brightest valid pixel's excess.
        margin: dilation of the region in binned pixels (the blurred rim).
        grow: binned pixels by which a core found at a higher level grows into the
            pixels above the first level.
        max_fraction: a region over this fraction of the valid pixels (dilated) is no
            compact object (a bright sky).
        min_solidity: nor is a region covering less than this fraction of its convex hull
            (a web of bright texture or noise over a bright, plain scene).
        min_share: the energy share a region found above a higher level must hold.

    Returns:
        (h, w) bool: at the first level that gives one, the 8-connected candidate region
        with the largest summed squared excess that is small and compact enough (and at
        the higher levels holds ``min_share``), grown and dilated; all False where no
        valid pixel exceeds the median or no level gives such a region.
    """
    import cv2

    none = np.zeros(image.shape, bool)
    if not valid.any():
        return none
    excess = np.where(valid, image - np.median(image[valid]), 0).astype(np.float32)
    peak = float(excess.max())
    if not peak > 0:
        return none
    for k, level in enumerate(levels):
        count, labels = cv2.connectedComponents((excess > level * peak).astype(np.uint8), connectivity=8)
        energy = np.bincount(labels.ravel(), weights=(excess * excess).ravel(), minlength=count)
        energy[0] = 0  # the background label
        blob = labels == int(np.argmax(energy))
        if k and energy.max() < min_share * energy.sum():
            continue
        hull = cv2.convexHull(np.argwhere(blob)[:, ::-1].astype(np.int32))
        if blob.sum() < min_solidity * cv2.contourArea(hull):
            continue
        if k:
            near = cv2.dilate(blob.astype(np.uint8), np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)) > 0
            blob |= near & (excess > levels[0] * peak)
        blob = cv2.dilate(blob.astype(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)) > 0
        if blob.sum() <= max_fraction * valid.sum():
            return blob
    return none


MOVER_DISAGREEMENT_PX = 0.5
"""Binned pixels by which a probe's shift without the brightest blob must differ from its
whole frames' shift to replace it (:func:`shift_without_mover`)."""

MOVER_MIN_CORRELATION = 0.8
"""Correlation the registration without the brightest blob must reach to replace a probe's
shift (:func:`shift_without_mover`): photon noise alone keeps a dark capture's below it."""


def shift_without_mover(a: NDArray[np.float32], b: NDArray[np.float32], shift: NDArray[np.float64],
                        correlation: float, min_correlation: float) -> tuple[NDArray[np.float64], float]:
    """The shift of two binned blocks, checked against a moving object's pull.

    The speed probe of :func:`~photonpano.budget.probe.probe_capture` uses it. Phase
    correlation whitens the spectrum, so the sharp rim of a bright object crossing a
    smooth scene can carry it to the object's motion; the 75th percentile of the probes'
    speeds then sizes the groups for that motion (objects_coffee crossed by a disc of
    radius 30 px at 0.08 px/frame: 0.041 px/frame probed, 0.027 without the disc: groups
    of 240 frames instead of 370, and 0.27 px RMSE instead of 0.16 with the static plan).
    The blocks are registered again by ECC (:func:`~photonpano.imaging.register_binned`, which weighs
    every pixel's contrast), without each block's :func:`brightest_blob`; the shift of
    the image centre found so replaces the phase correlation's where it correlates at
    :data:`MOVER_MIN_CORRELATION` or more and differs by more than
    :data:`MOVER_DISAGREEMENT_PX` in length (what it changed on the evaluation suite:
    ``docs/real_scenes.md``, "The speed probe").

    Args:
        a: (h, w) float32 binned sum of the first of two adjacent blocks.
        b: (h, w) float32 the same of the second.
        shift: (2,) float64 ``(dx, dy)`` of ``b`` relative to ``a`` by phase correlation,
            in binned pixels.
        correlation: the phase correlation's correlation after the shift.
        min_correlation: the probe's correlation limit.

    Returns:
        ``(shift, correlation)``: the shift and correlation to use.
    """
    valid = np.isfinite(a) & np.isfinite(b)
    blob_a, blob_b = brightest_blob(a, valid), brightest_blob(b, valid)
    h, cc, _ = register_binned((a, valid & ~blob_a), (b, valid & ~blob_b), np.eye(3), 1, from_initial=True)
    centre = np.array([(a.shape[1] - 1) / 2, (a.shape[0] - 1) / 2])
    moved = geometry.apply(h, centre[None])[0] - centre  # b's centre in a's pixels
    agree = abs(float(np.hypot(*moved)) - float(np.hypot(*shift))) <= MOVER_DISAGREEMENT_PX
    if cc < max(min_correlation, MOVER_MIN_CORRELATION) or agree:
        return shift, correlation
    return moved, float(cc)


def moving_fraction(pano: Panorama) -> tuple[float, float] | None:
    """Fractions of a panorama's covered canvas where its robust merge left observations out.

    Args:
        pano: a panorama; its ``moving`` mask is None from a compositor that merges
            every photon.

    Returns:
        ``(total, largest)`` in [0, 1]: all left-out covered pixels, and the largest
        8-connected region of them (a mover's path is one region; a slightly
        misregistered estimate leaves many small ones, e.g. around stars), over the
        covered pixels (``frames > 0``); None without a mask.
    """
    import cv2

    if pano.moving is None:
        return None
    covered = max(int(np.count_nonzero(pano.frames > 0)), 1)
    moving = (pano.moving & (pano.frames > 0)).astype(np.uint8)
    count, _, stats, _ = cv2.connectedComponentsWithStats(moving, connectivity=8)
    largest = int(stats[1:, cv2.CC_STAT_AREA].max()) if count > 1 else 0
    return round(int(np.count_nonzero(moving)) / covered, 6), round(largest / covered, 6)
