"""Which binning each step of a run registers at: level 1 (``registration_binning``) and the mosaic levels.

:func:`registration_binning` resolves the spec's ``registration_binning`` (``auto``:
:func:`auto_binning`, by frame size) for the pairwise levels; :func:`mosaic_binning` the
mosaic levels' ``mosaic.registration_binning`` (``auto``: full resolution on short,
well-lit captures). The binned capture itself is :mod:`photonpano.budget.grid`'s.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..stages import PhotonSource

if TYPE_CHECKING:
    from ..records import LocateResult

__all__ = ["auto_binning", "registration_binning", "mosaic_binning", "full_resolution_hint", "little_texture",
           "MIN_BINNED_SIDE", "FULL_RESOLUTION_MOSAIC_MAX", "FULL_RESOLUTION_MOSAIC_PHOTONS", "LITTLE_TEXTURE_RESCUED"]

MIN_BINNED_SIDE = 100
"""``registration_binning: auto`` bins only where the binned frames keep at least this many
pixels on their short side: registration precision comes from the number of pixels, and
on smaller frames (127x248, the super-resolution benchmark's) binning doubled the
trajectory error (0.10 -> 0.22 px)."""


def auto_binning(height: int, width: int) -> int:
    """The binning of ``registration_binning: auto``: 2 if frames stay >= :data:`MIN_BINNED_SIDE` pixels, else 1.

    Args:
        height: frame height in sensor pixels.
        width: frame width in sensor pixels.
    """
    return 2 if min(height, width) // 2 >= MIN_BINNED_SIDE else 1


def registration_binning(spec: Any, source: PhotonSource) -> int:
    """The spec's ``registration_binning`` for ``source`` (``auto`` resolved by :func:`auto_binning`).

    Raises:
        StageError: if the binning leaves frames smaller than 16 pixels.
    """
    from ..errors import StageError

    value = spec.registration_binning
    factor = auto_binning(source.height, source.width) if value == "auto" else int(value)
    if min(source.height, source.width) // factor < 16:
        raise StageError("spec", "registration_binning", f"binning {factor}x{factor} leaves frames of "
                         f"{source.height}x{source.width} pixels smaller than 16 pixels")
    return factor


FULL_RESOLUTION_MOSAIC_MAX = 6e9
"""``mosaic.registration_binning: auto`` merges and registers the mosaic levels at full
resolution only while the capture holds at most this many pixel-frames (frames x height
x width: 47 600 frames of 254x496, 22 900 of 512x512); longer captures keep the binned
mosaic, which holds 100 000 frames within their time budget (docs/performance.md) and is
within 0.09-0.19 px there on the evaluation suite."""

FULL_RESOLUTION_MOSAIC_PHOTONS = 10.0
"""... and only where a level-1 group gathers at least this many photons per sensor pixel
(the photon budget's light limit, :func:`~photonpano.budget.probe.choose_group_size`).

Measured on the evaluation suite (20 000-frame captures, every level's binning else as
before): where the groups had this much light, full resolution cut the trajectory RMSE
of 32 of the 35 captures by more than 0.005 px and raised none (city 0.060 -> 0.037 px,
chelsea 0.122 -> 0.083, clock 1.133 -> 0.724, coffee 0.180 -> 0.100) for about 1.35x the
CPU time (city: 20 -> 27 s of CPU for the run and its ground-truth check). Where they
had less (fast pans at 8.7-9.7 photons, flux 0.005 at 0.8, a dark scene at 1.8) the
noisier full-resolution frames either did worse (coffee at flux 0.005: 0.965 -> 1.420
px) or, registering more consistently with a wrong template, hid errors over 1 px from
the held-out check (four captures reported ``ok``)."""


def mosaic_binning(spec: Any, source: PhotonSource, register: int,
                   photons_per_pixel_per_group: float | None) -> tuple[int, str]:
    """The binning of the mosaic levels (spec ``mosaic.registration_binning``) and why.

    ``auto``: the binning ``register`` of level 1 where ``registration_binning`` is set in
    the spec (one binning for every level, as before this setting existed); else 1 where
    the capture holds at most :data:`FULL_RESOLUTION_MOSAIC_MAX` pixel-frames and a group
    gathers at least :data:`FULL_RESOLUTION_MOSAIC_PHOTONS` photons per pixel (intensity
    frames always do), else ``register``.

    Args:
        spec: a validated ``PipelineSpec``.
        source: the opened capture.
        register: the binning of level 1 (:func:`registration_binning`).
        photons_per_pixel_per_group: detections per sensor pixel in a level-1 group (the
            plan's; None for intensity frames).

    Returns:
        ``(k, reason)``: sensor pixels per merged-frame pixel per side at the mosaic levels
        (>= 1) and one line saying why.

    Raises:
        StageError: if the binning leaves frames smaller than 16 pixels.
    """
    from ..errors import StageError

    value = spec.mosaic.registration_binning
    if value != "auto":
        factor, reason = int(value), "set in the spec"
    elif spec.registration_binning != "auto":
        factor, reason = register, "auto: registration_binning is set in the spec, the mosaic levels follow it"
    else:
        pixel_frames = _pixel_frames(source)
        light = photons_per_pixel_per_group
        if _too_long(source):
            why = f"{pixel_frames:.3g} pixel-frames exceed {FULL_RESOLUTION_MOSAIC_MAX:.0e}"
        elif _too_dim(light):
            why = f"{light:.3g} photons per pixel per group, under {FULL_RESOLUTION_MOSAIC_PHOTONS:g}"
        else:
            why = None
        factor = register if why else 1
        reason = (f"auto: {why}: binned {register}x{register} as level 1" if why else
                  f"auto: full resolution ({pixel_frames:.3g} pixel-frames, "
                  + ("intensity frames)" if light is None else f"{light:.3g} photons per pixel per group)"))
    if min(source.height, source.width) // factor < 16:
        raise StageError("spec", "mosaic.registration_binning", f"binning {factor}x{factor} leaves frames of "
                         f"{source.height}x{source.width} pixels smaller than 16 pixels")
    return factor, reason


def _pixel_frames(source: PhotonSource) -> float:
    """Frames x height x width of ``source``."""
    return float(source.n_frames) * source.height * source.width


def _too_long(source: PhotonSource) -> bool:
    """Whether ``auto`` bins the mosaic levels of ``source`` for its length (:data:`FULL_RESOLUTION_MOSAIC_MAX`)."""
    return _pixel_frames(source) > FULL_RESOLUTION_MOSAIC_MAX


def _too_dim(photons_per_pixel_per_group: float | None) -> bool:
    """Whether ``auto`` bins the mosaic levels for light (:data:`FULL_RESOLUTION_MOSAIC_PHOTONS`; None: never)."""
    light = photons_per_pixel_per_group
    return light is not None and light < FULL_RESOLUTION_MOSAIC_PHOTONS


def full_resolution_hint(spec: Any, source: PhotonSource, mosaic: int,
                         photons_per_pixel_per_group: float | None) -> str | None:
    """Where ``auto`` binned the mosaic levels for the capture's length alone, the line saying so; else None.

    On a long capture (over :data:`FULL_RESOLUTION_MOSAIC_MAX` pixel-frames) whose groups
    gather enough light for full resolution (:data:`FULL_RESOLUTION_MOSAIC_PHOTONS`), the
    binning saves time, not noise, and on a scene of little texture it is what limits the
    accuracy (100 000 frames of the evaluation suite's clock on the zigzag path: 0.295 px
    binned, a median predicted error of 0.32 px and ``degraded``; 0.131 px and 0.09 px at
    full resolution in 41 s instead of 23; three smooth photos outside the suite alike,
    from ``degraded`` to ``ok``; docs/performance.md). The levels stay binned, which keeps
    the suite's 15 other photos within 0.15 px in about half the time, unless the held-out
    registrations predict frames above the limit: :func:`~photonpano.pipeline.reconstruct`
    then runs the mosaic levels again at full resolution from level 1; a run ``degraded``
    otherwise gets this line in its notes.

    Args:
        spec: a validated ``PipelineSpec``.
        source: the opened capture.
        mosaic: the mosaic levels' binning (:func:`mosaic_binning`).
        photons_per_pixel_per_group: detections per sensor pixel in a level-1 group (None
            for intensity frames).

    Returns:
        One line, or None where the binning was set in the spec, was chosen for light, or is 1.
    """
    if (mosaic == 1 or spec.mosaic.registration_binning != "auto" or spec.registration_binning != "auto"
            or not _too_long(source) or _too_dim(photons_per_pixel_per_group)):
        return None
    return (f"the mosaic levels registered frames binned {mosaic}x{mosaic} to save time on this long capture "
            f"({_pixel_frames(source):.3g} pixel-frames); on a scene of little texture that binning limits the "
            "accuracy, and mosaic.registration_binning: 1 registers them at full resolution in about twice the "
            "time (100 000 frames of a clock: 0.295 -> 0.131 px)")


LITTLE_TEXTURE_RESCUED = 0.9
"""Fraction of level 1's pairs that its check had to register directly (the locator's
features failed them, :class:`~photonpano.schemes.check.PairCheck`) from which a long
capture's mosaic levels register at full resolution from the start (:func:`little_texture`)."""


def little_texture(located: LocateResult) -> str | None:
    """Where level 1's features failed on a scene of little texture, the line saying so; else None.

    On a long capture whose mosaic levels ``auto`` binned for its length alone
    (:func:`full_resolution_hint`), such a scene's binned mosaic levels leave frames
    predicted above the uncertainty's limit, and :func:`~photonpano.pipeline.reconstruct`
    runs them again at full resolution. Where level 1's check rescued at least
    :data:`LITTLE_TEXTURE_RESCUED` of its pairs, the run (``Stages.estimate_motion``)
    registers them at full resolution from level 2 on instead: the same trajectory, less
    the binned levels' time (about 6 s of the evaluation suite's clock's 100 000 frames, 49 ->
    43 s; docs/performance.md, "The clock's 100 000 frames: 48 -> 38 s").

    Args:
        located: level 1's :class:`~photonpano.records.LocateResult` (its ``check`` figures
            and ``pair_index``).

    Returns:
        One line (for the budget's ``mosaic_binning`` reason and the run's notes), or None.
    """
    rescued = (located.check or {}).get("rescued") or 0
    pairs = 0 if located.pair_index is None else len(located.pair_index)
    if pairs < 1 or rescued < LITTLE_TEXTURE_RESCUED * pairs:
        return None
    return (f"auto: level 1's features failed on {rescued} of its {pairs} pairs (a scene of little texture, "
            "which the binned mosaic levels leave above the uncertainty's limit): registered at full resolution "
            "from level 2")
