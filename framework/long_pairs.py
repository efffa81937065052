"""Held-out registrations far apart in time: the shape error that neighbouring frames share.

The held-out pairs of :mod:`photonpano.uncertainty` register *consecutive* merged frames,
so they see the change of the trajectory's error from one group to the next. An error that
grows slowly along the capture (a shear or keystone ramp: a turning camera's focal length
estimated 1 % off, a moving object that bent level 1's chain) changes by less than their
noise between neighbours, and the mosaic levels' template holds it too, so neither sees it.
The last level therefore also registers *chains* of merged frames far apart
(:func:`long_baseline_chains`: from the first full group to the last, each link as long as
the frames still overlap well; about 40 registrations), directly against each other.
Summed along a chain, the links' disagreements with the final trajectory give its shape
error (:func:`chain_shape_error`); the chains' spread gives the noise of that estimate.

A link over 70 % overlap is 2-3 times noisier than a consecutive pair (the facade's
bricks: 0.11 px against the truth, its consecutive pairs 0.033 px; the sunset at flux
0.05 on a zigzag: 0.3-2 px), so one chain alone over-predicts a static capture's error
threefold. :data:`CHAINS` independent chains estimate the noise of their mean from their
spread, and only what stands :data:`SIGNIFICANCE` standard errors above it counts:
measured with default settings, the city's median sigma 0.019 -> 0.020 px (RMSE 0.013),
chelsea's 0.030 -> 0.030 (0.021), Hubble's 0.035 -> 0.038 (0.027), the sunset's zigzag at
flux 0.05 0.199 -> 0.219 (0.115; with four chains and the spread taken off once, 0.55),
while a 50-degree tripod pan's keystone ramp over the city (0.314 px) is predicted at a
median 0.231 px instead of 0.087 (frames within twice their sigma 28 -> 72 %) and a facade
crossed by a bright disc (0.144 px) at 0.071 instead of 0.065 (52 -> 84 %).

Each link is registered both ways and to convergence (:func:`register_links`,
:func:`links_both_ways`, :meth:`~photonpano.locator.LocatorConfig.converging`): stopped at
the mosaic locator's speed-tuned rule, a link kept part of the current estimate's error, and
one way only, the low-texture clock's links carried a bias that follows the warped frame.

What the chains agree on is also taken out of the trajectory (:func:`correct_shape_drift`, on by default);
the shape term is what they still disagree on, and on fast pans what they cannot resolve (their noise).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import geometry
from .locator import Locator, LocatorContext
from .records import MergedFrames, PairRegistrations

__all__ = ["SIGNIFICANCE", "CHAINS", "LINK_EXTENT", "MAX_LINK_FRACTION", "DRIFT_SIGNIFICANCE", "DRIFT_STEPS",
           "DRIFT_TOLERANCE_PX", "long_baseline_chains", "register_links", "links_both_ways", "chain_shape_error",
           "correct_shape_drift"]

LINK_EXTENT = 0.3
"""Longest link of :func:`long_baseline_chains`, in frame extents travelled between its two
reference frames (0.3: the two frames overlap by 70 %)."""

MAX_LINK_FRACTION = 0.25
"""Longest link in groups, as a fraction of the level's groups (at least four links)."""

SIGNIFICANCE = 2.0
"""Standard errors of the chains' mean (their spread over the square root of their number) taken off its size."""

DRIFT_STEPS = 5
"""Most steps of :func:`correct_shape_drift` (each first order; three reach the chains' solution on tripod pans)."""

DRIFT_SIGNIFICANCE = 3.0
"""Standard errors a parameter of the chains' mean error must stand at for :func:`correct_shape_drift` to
take any of it out (the gain ``1 - (DRIFT_SIGNIFICANCE * standard error)^2 / power``). The chains
register different groups of the same scene, so their errors are not independent and their spread
under-estimates the noise of their mean. With the links registered one way, the low-texture
clock's chains agreed on a horizontal scale drift at 5.8 that is not there, so this was 6; both
ways (:func:`links_both_ways`) that drift is gone, and on the evaluation suite at 3 no capture
got worse and 10 got better (the facade's fast pan 0.829 -> 0.461 px, a 100 Hz lamp over the
city 0.026 -> 0.017), as did the tripod pans (the astronaut 0.185 -> 0.108; docs/accuracy.md).
On 38 of the suite's 48 captures the largest parameter stands at 1.4-3.4; a tripod pan's keystone
and scale ramps at 12-26 (power / noise 150-670). Much lower takes out errors the chains share: the
sunset at flux 0.05, whose chains share a perspective error at 2.6, went 0.115 -> 0.404 px at 1."""

DRIFT_TOLERANCE_PX = 0.005
"""A step of :func:`correct_shape_drift` that moves no frame by more (mean corner distance, px) is the last."""

CHAINS = 8
"""Chains of links; chain m's first link is m / CHAINS of a whole one, so the chains register
different pairs of groups and their spread measures the links' noise."""


def long_baseline_chains(references: NDArray[np.float64], lengths: NDArray[np.int64], width: int,
                         height: int) -> NDArray[np.int64]:
    """The held-out chains' links: from the first full group to the last, each link as long as the frames overlap well.

    A link joins two groups at most ``MAX_LINK_FRACTION * G`` groups and
    :data:`LINK_EXTENT` frame extents apart (the farthest such group; the next group where
    even that one is farther). Chain ``m`` of :data:`CHAINS` makes its first link
    ``m / CHAINS`` of a full one, so the chains' links are different registrations of
    different groups in between. The short anchor groups at the capture's ends
    (``midpoint``'s ``anchor_ends``: fewer photons, noisier registrations) are left out.

    Args:
        references: (G, 3, 3) float64 the current frame-to-panorama homographies of the
            groups' reference frames, in capture order.
        lengths: (G,) int64 the groups' lengths in frames.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        (P, 3) int64 links ``(chain, a, b)``, group ``b`` after group ``a``, in chain order;
        empty where G < 8 (the consecutive pairs see the whole capture).
    """
    if len(references) < 8:
        return np.zeros((0, 3), np.int64)
    full = np.flatnonzero(lengths >= np.median(lengths))
    first, last = int(full[0]), int(full[-1])
    centre = np.array([width / 2.0, height / 2.0, 1.0])
    mapped = references @ centre
    centres = mapped[:, :2] / mapped[:, 2:]
    longest = max(2, int(MAX_LINK_FRACTION * len(references)))

    def farthest(a: int, limit: int) -> int:
        apart = geometry.extents_apart(centres[a + 1:min(last, a + limit) + 1] - centres[a], width, height)
        near = np.flatnonzero(apart <= LINK_EXTENT)
        return a + 1 + (int(near[-1]) if len(near) else 0)

    links = []
    whole = farthest(first, longest) - first  # a whole first link (the overlap may limit it, not the groups)
    for m in range(CHAINS):
        a, limit = first, max(1, whole * m // CHAINS) if m else longest
        while a < last:
            b = farthest(a, limit)
            links.append((m, a, b))
            a, limit = b, longest
    return np.asarray(links, np.int64).reshape(-1, 3)


def register_links(locator: Locator, merged: MergedFrames, pairs: NDArray[np.int64],
                   expected: NDArray[np.float64], *, backward: bool = False) -> PairRegistrations:
    """Register the chains' links one way: b's pixels to a's, or (``backward``) a's to b's, returned inverted.

    Args:
        locator: the chains' locator.
        merged: the merged frames ``pairs`` index.
        pairs: (P, 2) int64 positions ``(a, b)`` in ``merged``.
        expected: (P, 3, 3) float64 the current estimate of each link, b's pixels to a's.
        backward: register a's pixels to b's (from the inverse of ``expected``) and invert.

    Returns:
        P registrations, b's pixels to a's either way (:func:`links_both_ways` takes their mean).
    """
    if not backward:
        return locator.register_pairs(merged, pairs, expected, LocatorContext())
    found = locator.register_pairs(merged, pairs[:, ::-1], geometry.invert(expected), LocatorContext())
    return PairRegistrations(geometry.invert(found.homographies), found.matches, found.inliers, found.ok)


def links_both_ways(forward: PairRegistrations, backward: PairRegistrations, expected: NDArray[np.float64],
                    width: int, height: int) -> PairRegistrations:
    """Each link as the mean of its registrations both ways (:func:`register_links`).

    A direct registration of two frames that overlap by only about 70 % is biased by
    which of them is warped, and the low-texture clock's smooth frames show it: its 39
    links (``interior_clock/wander``, flux 0.5, 2026-11-27, ECC run to convergence:
    :meth:`~photonpano.locator.LocatorConfig.converging`) measured the horizontal scale
    0.363 px off the truth on average one way, -0.253 px the other, 0.054 px their mean
    (each link's corner RMS in that parameter 0.507, 0.458 and 0.261 px), and their
    chains agreed on a scale drift of 1.6 px along the capture that is not there. The
    mean is taken over the 8 parameters of each registration's change from ``expected``,
    about the frame centre (first order in the change).

    Args:
        forward: the links' registrations b's pixels to a's.
        backward: the same links registered a's pixels to b's, inverted.
        expected: (P, 3, 3) float64 the current estimate of each link.
        width: frame width in pixels (the merged frames are in their reference frame's grid).
        height: frame height in pixels.

    Returns:
        P registrations, b's pixels to a's; ok where both ways registered.
    """
    change = (_link_change(forward.homographies, expected, width, height)
              + _link_change(backward.homographies, expected, width, height)) / 2
    mean = geometry.from_centre(geometry.homographies_from_params(change), width, height)
    return PairRegistrations(geometry.normalize(expected @ mean), forward.matches, forward.inliers,
                             forward.ok & backward.ok)


def _link_change(registrations: NDArray[np.float64], expected: NDArray[np.float64], width: int,
                 height: int) -> NDArray[np.float64]:
    """(P, 8) float64 each link's registration as a change from ``expected``: p1..p8 about the frame centre."""
    return geometry.params_from_homographies(geometry.about_centre(
        geometry.invert(expected) @ registrations, width, height))


def _chain_errors(registrations: NDArray[np.float64], ok: NDArray[np.bool_], links: NDArray[np.int64],
                  references: NDArray[np.int64], expected: NDArray[np.float64], width: int, height: int
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Each chain's estimate of the trajectory's error along it (see :func:`chain_shape_error`).

    ``expected`` is (P, 3, 3) float64 the trajectory's homography along each link (group
    b's reference frame's pixels to group a's); the other arguments are :func:`chain_shape_error`'s.

    Returns:
        ``(nodes, errors)``: (N,) float64 the frames where a kept chain's link starts or
        ends, increasing, and (M, N, 8) float64 each kept chain's error there, as 8
        parameters about the frame centre (frame-side: ``H = H_true @ E``), linear in
        between and constant beyond the chain's own ends, with its mean over the frames
        from ``nodes[0]`` to ``nodes[-1]`` subtracted (:func:`_frame_sums`); None where
        fewer than two chains have every link registered.
    """
    chains = [m for m in np.unique(links[:, 0]) if ok[links[:, 0] == m].all()]
    if len(chains) < 2:
        return None
    kept = np.isin(links[:, 0], chains)
    links, registrations, expected = links[kept], registrations[kept], expected[kept]
    start, stop = references[links[:, 1]], references[links[:, 2]]
    change = _link_change(registrations, expected, width, height)
    nodes = np.unique(np.concatenate([start, stop])).astype(np.float64)
    along = []
    for m in chains:
        mine = links[:, 0] == m
        at = np.concatenate([start[mine][:1], stop[mine]]).astype(np.float64)
        # the disagreements sum to the error at the chain's first frame minus that at each later one
        error = -np.vstack([np.zeros((1, 8)), np.cumsum(change[mine], axis=0)])
        along.append(_interpolate(nodes, at, error))
    errors = np.stack(along)
    linear = _frame_sums(nodes)[0]
    return nodes, errors - (np.einsum("n,mnk->mk", linear, errors) / linear.sum())[:, None]


def _interpolate(frames: NDArray[np.float64] | NDArray[np.int64], nodes: NDArray[np.float64],
                 values: NDArray[np.float64]) -> NDArray[np.float64]:
    """(..., F, 8) ``values`` (..., N, 8) at increasing ``nodes`` (N,) at ``frames`` (F,): :func:`numpy.interp`.

    Linear in between, constant beyond the first and last node.
    """
    flat = values.reshape(-1, len(nodes), values.shape[-1])
    out = np.empty((len(flat), len(frames), values.shape[-1]))
    for m, chain in enumerate(flat):
        for k in range(values.shape[-1]):
            out[m, :, k] = np.interp(frames, nodes, chain[:, k])
    return out.reshape(values.shape[:-2] + out.shape[1:])


def _frame_sums(nodes: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Weights of the sums over the whole frames ``nodes[0]..nodes[-1]`` of functions linear between ``nodes``.

    A function with values ``y`` at the (N,) increasing whole-frame ``nodes`` sums to
    ``linear @ y`` over those frames, and its square to ``diag @ y^2 + 2 off @ (y[:-1] y[1:])``
    (the sums of ``t / L`` and ``(t / L)^2`` over the ``L`` frames ``t`` of each segment, in
    closed form): the means :func:`correct_shape_drift` takes without evaluating the chains at
    every frame of a 100 000-frame capture.

    Returns:
        ``(linear, diag, off)``: (N,), (N,) and (N - 1,) float64 weights.
    """
    length = np.diff(nodes)
    first = (length - 1) / 2  # sum over t < L of t / L
    second = (length - 1) * (2 * length - 1) / (6 * length)  # of (t / L)^2
    linear, diag = np.zeros(len(nodes)), np.zeros(len(nodes))
    linear[:-1] += length - first
    linear[1:] += first
    diag[:-1] += length - 2 * first + second
    diag[1:] += second
    linear[-1] += 1
    diag[-1] += 1
    return linear, diag, first - second


def _frame_mean_squares(nodes: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    """(..., 8) the mean square over the whole frames ``nodes[0]..nodes[-1]`` of ``values`` (..., N, 8)."""
    linear, diag, off = _frame_sums(nodes)
    sums = (np.einsum("n,...nk->...k", diag, values ** 2)
            + 2 * np.einsum("n,...nk->...k", off, values[..., :-1, :] * values[..., 1:, :]))
    return sums / linear.sum()


def _size(params: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    """Mean corner distance in pixels of the homographies of ``params`` (..., 8) about the centre from the identity."""
    p = np.moveaxis(np.asarray(params, np.float64), -1, 0)  # elementwise, no 3x3 stacks: 8 chains x 100 000 frames
    cx, cy, total = (width - 1) / 2, (height - 1) / 2, np.zeros(p.shape[1:])
    for x, y in ((-cx, -cy), (cx, -cy), (cx, cy), (-cx, cy)):  # corners about the centre
        scale = p[6] * x + p[7] * y + 1
        total += np.hypot(((1 + p[0]) * x + p[2] * y + p[4]) / scale - x,
                          (p[1] * x + (1 + p[3]) * y + p[5]) / scale - y)
    return total / 4


def chain_shape_error(registrations: NDArray[np.float64], ok: NDArray[np.bool_], links: NDArray[np.int64],
                      references: NDArray[np.int64], homographies: NDArray[np.float64], width: int,
                      height: int) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Each frame's shape error, from the held-out chains' disagreements with the final trajectory.

    A link registers group ``b``'s merged frame to group ``a``'s; its disagreement with the
    homography the final trajectory implies between their reference frames, as 8
    parameters about the frame centre, is the change of the trajectory's error along the
    link plus registration noise. Summed along a chain, the changes give the error at each
    of its frames relative to the first, linear in between; the mean over the frames the
    chains span (the part a global alignment of the trajectory removes, as
    :func:`~photonpano.metrics.trajectory_error` does) is subtracted. The chains' mean is
    the estimate and their spread over the square root of their number its standard error;
    :data:`SIGNIFICANCE` standard errors are taken off its size in quadrature (a trajectory
    whose chains agree with it within their noise gets no shape error). That standard error,
    the shape error the chains cannot resolve, is returned too (for the uncertainty's shape term).

    Args:
        registrations: (P, 3, 3) float64 each link's registration (group b's pixels to a's).
        ok: (P,) bool links that registered.
        links: (P, 3) int64 ``(chain, a, b)`` of :func:`long_baseline_chains`.
        references: (G,) int64 the groups' reference frames.
        homographies: (T, 3, 3) float64 the final frame-to-panorama homographies.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``(shape, standard_error)``: (T,) float64 each, per frame in pixels (mean corner
        distance; constant beyond the chains' ends), or None where fewer than two chains have
        every link registered (a chain with a failed link is left out).
    """
    found = _chain_errors(registrations, ok, links, references, _along_links(homographies, links, references),
                          width, height)
    if found is None:
        return None
    nodes, errors = found
    frames = np.arange(nodes[0], nodes[-1] + 1)
    stacked = _interpolate(frames, nodes, errors)  # (M, F, 8)
    mean = stacked.mean(axis=0)
    spread = np.sqrt(np.mean([_size(e - mean, width, height) ** 2 for e in stacked], axis=0) / (len(stacked) - 1))
    shape = np.sqrt(np.maximum(_size(mean, width, height) ** 2 - SIGNIFICANCE ** 2 * spread ** 2, 0.0))
    every = np.arange(len(homographies), dtype=np.float64)
    return np.interp(every, frames, shape), np.interp(every, frames, spread)


def correct_shape_drift(registrations: NDArray[np.float64], ok: NDArray[np.bool_], links: NDArray[np.int64],
                        references: NDArray[np.int64], homographies: NDArray[np.float64], width: int,
                        height: int) -> tuple[NDArray[np.float64], float]:
    """Take the shape error the chains agree on out of the trajectory.

    The chains' mean error (:func:`chain_shape_error`'s estimate) is removed from every
    frame (``H <- H @ inv(E)``, ``E`` the error interpolated between the chains' frames,
    constant beyond them), each of the 8 parameters scaled by the gain
    ``max(0, 1 - DRIFT_SIGNIFICANCE^2 noise / power)`` (``power`` the parameter's mean
    square over the frames, ``noise`` that of its standard error, the chains' spread over
    the square root of their number; a Wiener gain at :data:`DRIFT_SIGNIFICANCE` 1): a
    parameter in which the chains agree with the trajectory within 3 standard errors is
    left as it is. The links' disagreements are first order in the error, so the step is
    repeated against the corrected trajectory (at most :data:`DRIFT_STEPS` times, until a
    step moves no frame's corners by more than :data:`DRIFT_TOLERANCE_PX` on average).

    What it corrects is the error the consecutive registrations and the mosaic template
    cannot see (module docstring): measured with default settings on 20 000-frame captures,
    a 50-degree tripod pan (``source.pan_model: rotation``) over the city 0.314 px uncorrected
    -> 0.075 px, the mountains 0.225 -> 0.064, the gravel 0.158 -> 0.043, the astronaut
    0.494 -> 0.108 (docs/accuracy.md).

    Args:
        registrations: (P, 3, 3) float64 each link's registration (group b's pixels to a's).
        ok: (P,) bool links that registered.
        links: (P, 3) int64 ``(chain, a, b)`` of :func:`long_baseline_chains`.
        references: (G,) int64 the groups' reference frames.
        homographies: (T, 3, 3) float64 frame-to-panorama homographies.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``(corrected, moved_px)``: (T, 3, 3) float64 homographies (the input where fewer than
        two chains registered every link) and the largest mean corner distance by which the
        correction moved a frame, in pixels.
    """
    corrected = np.asarray(homographies, np.float64)
    # the chains read the trajectory at the links' reference frames only: correct it there
    # step by step, and every frame once the steps are known
    ends = np.unique(references[links[:, 1:]])
    at_ends, rows = corrected[ends], np.searchsorted(ends, references)  # a linked group's row in ``at_ends``
    steps: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    for _ in range(DRIFT_STEPS):
        found = _chain_errors(registrations, ok, links, references, _along_links(at_ends, links, rows), width, height)
        if found is None:
            break
        nodes, stacked = found
        mean = stacked.mean(axis=0)  # (N, 8)
        noise = _frame_mean_squares(nodes, stacked - mean).sum(axis=0) / (len(stacked) - 1) / len(stacked)
        power = _frame_mean_squares(nodes, mean)
        gain = np.clip(1.0 - DRIFT_SIGNIFICANCE ** 2 * noise / np.maximum(power, 1e-300), 0.0, 1.0)
        step = mean * gain
        steps.append((nodes, step))
        at_ends = _corrected(at_ends, ends, nodes, step, width, height)
        if _size(step, width, height).max() <= DRIFT_TOLERANCE_PX:
            break
    if not steps:
        return corrected, 0.0
    frames = np.arange(len(corrected))
    for nodes, step in steps:
        corrected = _corrected(corrected, frames, nodes, step, width, height)
    return corrected, float(_size(np.sum([step for _, step in steps], axis=0), width, height).max())


def _along_links(homographies: NDArray[np.float64], links: NDArray[np.int64], rows: NDArray[np.int64]
                 ) -> NDArray[np.float64]:
    """(P, 3, 3) the trajectory's homography along each link: ``inv(H[rows[a]]) @ H[rows[b]]``."""
    return geometry.invert(homographies[rows[links[:, 1]]]) @ homographies[rows[links[:, 2]]]


def _corrected(homographies: NDArray[np.float64], frames: NDArray[np.int64], nodes: NDArray[np.float64],
               step: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    """``homographies`` (F, 3, 3) of ``frames`` less the error ``step`` ((N, 8) at ``nodes``): ``H @ inv(E)``."""
    error = geometry.from_centre(geometry.homographies_from_params(_interpolate(frames, nodes, step)), width, height)
    return geometry.normalize(homographies @ geometry.invert(error))
