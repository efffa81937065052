"""Whether a level's registrations turn the camera: the signal of a shape parameter, and a steady keystone.

A camera that turns out of the image plane (on a tripod, or a hand-held turn) adds a
perspective to each registration between its frames; one that only slides adds none, and
a registration's perspective is then noise. Read one registration at a time the two look
alike; read over a level's registrations, in the order they were made, a turn changes
smoothly or steadily while noise does not. :class:`~photonpano.schemes.check.LevelCheck`
decides its rescues' perspective so, and :func:`~photonpano.schemes.pairwise.drop_unsteady_perspective`
its registered pairs'; :func:`rescue_motion` whether its rescues scale one axis without turning.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .. import geometry

__all__ = ["SIGNAL_LAG1", "SIGNAL_T", "KEYSTONE_PX", "shape_signal", "keystones", "steady_keystone", "rescue_motion"]

SIGNAL_LAG1 = 0.6
"""Lag-1 autocorrelation from which a shape parameter of the level's rescues, in the order
they were registered, counts as a signal: a change that is smooth along the capture
correlates from pair to pair, the noise of independent registrations does not (at 0.6 the
smooth part holds more than half the variance)."""
SIGNAL_T = 3.0
"""Standard errors from zero at which a shape parameter's mean over the level's rescues
counts as a signal (a steady change)."""
KEYSTONE_PX = 1.0
"""Median keystone (pixels at the frame's corner) a level's homography refinements of its
rescues must add to their affine registrations, besides a signal (:data:`SIGNAL_LAG1`,
:data:`SIGNAL_T`), for the level to keep them (:meth:`~photonpano.schemes.check.LevelCheck.settle`).
A camera on a tripod turning 50 degrees at f = 420 px: 2.9-4.4 px; a zigzag over the dark
Hubble photo, where a steady bias of the refinements reaches 4.6 standard errors: 0.14 px."""


def shape_signal(values: NDArray[np.float64]) -> dict[str, float | bool]:
    """A shape parameter over a level's registrations: lag-1 autocorrelation, t of its mean, and whether either counts.

    Args:
        values: (R,) float64 the parameter per registration, in the order they were made (R >= 2).

    Returns:
        ``{"lag1", "t", "signal"}``: ``signal`` where ``lag1 >= SIGNAL_LAG1`` or ``|t| >= SIGNAL_T``.
    """
    centred = values - values.mean()
    lag1 = float((centred[1:] * centred[:-1]).sum() / max(float((centred ** 2).sum()), 1e-300))
    t = float(values.mean() / max(float(values.std(ddof=1)) / np.sqrt(len(values)), 1e-300))
    return {"lag1": round(lag1, 3), "t": round(t, 2), "signal": lag1 >= SIGNAL_LAG1 or abs(t) >= SIGNAL_T}


def keystones(homographies: NDArray[np.float64], affine: NDArray[np.float64], width: int, height: int
              ) -> NDArray[np.float64]:
    """The perspective ``homographies`` add to ``affine``: ``p7 ((w - 1)/2)^2``, ``p8 ((h - 1)/2)^2`` about the centre.

    Args:
        homographies: (..., 3, 3) float64 registrations (frame pixels to frame pixels).
        affine: (..., 3, 3) float64 the affine maps they are read against (the identity: their own perspective).
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (..., 2) float64 the horizontal and vertical keystones, pixels at the frame's corner.
    """
    d = geometry.about_centre(homographies @ np.linalg.inv(affine), width, height)
    return d[..., 2, :2] / d[..., 2:, 2] * (np.array([width - 1, height - 1]) / 2) ** 2


def steady_keystone(values: NDArray[np.float64]) -> tuple[dict[str, dict[str, float | bool]], bool]:
    """Whether a level's keystones change steadily, as a turning camera's do.

    Args:
        values: (R, 2) float64 :func:`keystones` of the level's registrations, in the order they were made.

    Returns:
        ``(figures, steady)``: ``{"horizontal", "vertical"}``, each :func:`shape_signal`'s with
        ``median_px`` (of the keystone's size), and whether one carries a signal with a median
        of :data:`KEYSTONE_PX` or more.
    """
    tilts = {name: {**shape_signal(values[:, k]), "median_px": round(float(np.median(np.abs(values[:, k]))), 3)}
             for k, name in enumerate(("horizontal", "vertical"))}
    return tilts, any(tilt["signal"] and tilt["median_px"] >= KEYSTONE_PX for tilt in tilts.values())


def rescue_motion(shapes: NDArray[np.float64]) -> tuple[str, dict[str, dict[str, float | bool]]]:
    """Whether a level's rescues keep their affine corrections or take translations.

    A camera's zoom scales both axes alike. A level whose rescues scale one axis alone
    (zoom and anisotropy each carry a signal, ``shape_signal``: lag-1 autocorrelation >=
    :data:`SIGNAL_LAG1` or a mean :data:`SIGNAL_T` standard errors from zero) and do not
    turn (the rotation carries none) is taking up a direction its frames do not pin:
    every rescue then takes its translation. On the checkerboard panned at flux 0.5 the
    zoom's t is -9.8, the anisotropy's -10.0, the rotation's -1.5 (lag-1 0.46): 0.540 ->
    0.075 px, and under a 100 Hz lamp 0.605 -> 0.038 px.

    Anything else keeps each rescue's better registration. No signal is no evidence
    that the camera does not turn: a turning capture whose rescues' rotation is lost in
    their noise needs the affine corrections (in an experiment that decided such levels
    for translations, turning microaneurysms went from 0.31 to 2.66 px); and a level that
    turns keeps its rescues' one-axis scale with the turn (the checkerboard turning by up
    to 10 degrees: 0.51 px, 5.6 with translations). ``docs/accuracy.md``, "Rescues decided
    together".

    Args:
        shapes: (R, 4) float64 each rescue's rotation, zoom, anisotropy and shear
            (:mod:`~photonpano.schemes.check`'s ``_shape``, pixels at the frame's half
            width), in the order the pairs were registered; R >= 2.

    Returns:
        ``(motion, figures)``: ``"translation"`` or ``"per pair"`` (each rescue keeps its
        better registration), and ``{"rotation", "zoom", "anisotropy"}`` each ``{"lag1",
        "t", "signal"}``.
    """
    figures = {name: shape_signal(shapes[:, k]) for k, name in enumerate(("rotation", "zoom", "anisotropy"))}
    one_axis = figures["zoom"]["signal"] and figures["anisotropy"]["signal"] and not figures["rotation"]["signal"]
    return ("translation" if one_axis else "per pair"), figures
