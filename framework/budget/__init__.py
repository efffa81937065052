"""The photon budget of a capture: how many photons each step of a run gathers, decided once.

A SPAD capture has few photons per binary frame; every step that looks at images gathers
them over frames (the group size m) or over pixels (a binning). :class:`Budget` holds the
four choices of one capture and why each was made, and is recorded in ``run.json``
(``budget``):

- **group size** m: binary frames per virtual exposure at level 1
  (:func:`~photonpano.budget.probe.plan_group_size`: set in the spec, or chosen from the
  capture's light and speed);
- **registration binning** k: sensor pixels per side summed into a merged-frame pixel
  before the pairwise levels merge and register (spec ``registration_binning``;
  :mod:`photonpano.budget.binnings`), and its value at the mosaic levels (spec
  ``mosaic.registration_binning``: full resolution where the capture is short enough and
  a group gathers enough light);
- **check binning** c: merged-frame pixels per side of the binned images on which the
  pairwise scheme checks, and rescues, its level-1 pairs (:class:`~photonpano.schemes.check.PairCheck`;
  with ``group_size: auto`` only);
- **agreement binning** a: pixels per side of the images on which merged frames are
  compared with the finished panorama (:func:`~photonpano.quality.panorama_agreement`).

Every image of these steps is binned on one block grid (:mod:`photonpano.imaging`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .binnings import auto_binning, mosaic_binning, registration_binning
from .probe import CaptureProbe, GroupPlan, plan_group_size

__all__ = ["Budget", "GroupPlan", "CaptureProbe", "agreement_binning", "check_binning", "auto_binning",
           "saturation_note", "SATURATED"]


SATURATED = 0.99
"""Mean detections per pixel per binary frame from which :func:`saturation_note` calls a capture saturated."""


def saturation_note(probe: CaptureProbe | None) -> str | None:
    """For a capture whose pixels detect a photon in nearly every binary frame: why no pair registers.

    Where ``1 - exp(-phi tau)`` is near 1 everywhere, a merged frame counts the few frames
    without a detection and its flux is mostly noise (a simulated capture at 1 000 dark
    counts per pixel per frame: "all 39 pairs of merged frames failed to register").

    Args:
        probe: the capture's :func:`probe_capture` (None, or an intensity source's: no note).

    Returns:
        One line: the detection rate and the remedy; None below :data:`SATURATED`.
    """
    ones = probe.photons_per_pixel_per_frame if probe is not None else None
    if ones is None or ones < SATURATED:
        return None
    return (f"the capture is saturated: its pixels detect a photon in {ones:.1%} of the binary frames, so a "
            "merged frame holds little but noise (less light is needed: a shorter exposure or a neutral-density "
            "filter)")


def agreement_binning(plan: GroupPlan, photons: float = 20.0) -> int:
    """Binning giving a level-1 merged frame about ``photons`` detections per pixel (2 to 8).

    Args:
        plan: the capture's group-size plan (its ``photons_per_pixel_per_group``; None
            for intensity sources, which get 2).
        photons: detections per binned pixel wanted.
    """
    per_group = plan.photons_per_pixel_per_group
    if per_group is None:
        return 2
    return int(min(8, max(2, math.ceil(math.sqrt(photons / max(per_group, 1e-12))))))


def check_binning(plan: GroupPlan, register_binning: int) -> int | None:
    """Merged-frame pixels per side of the level-1 pair check, or None for no check.

    The check runs with ``group_size: auto`` only (explicit group sizes keep the plain
    locator); it bins sensor pixels in blocks of at least 2 (more where the plan's
    photon deficit asks for it, ``plan.binning``), counted in merged-frame pixels.

    Args:
        plan: the capture's group-size plan.
        register_binning: sensor pixels per merged-frame pixel per side (>= 1).
    """
    if not plan.auto:
        return None
    return max(1, round(max(2, plan.binning) / register_binning))


@dataclass(frozen=True)
class Budget:
    """The photon budget of one capture (see the module): frames per group and four binnings.

    Attributes:
        plan: the :class:`~photonpano.budget.probe.GroupPlan` (group size m, why, the
            pre-pass's figures, the flicker found); ``run.json``'s ``group_size`` entry.
        register_binning: sensor pixels per side of a merged-frame pixel at the pairwise
            levels (>= 1).
        mosaic_binning: the same at the mosaic levels (>= 1).
        check_binning: merged-frame pixels per side of the level-1 pair check's images,
            or None when no check runs.
        agreement_binning: pixels per side of the panorama agreement's images (2 to 8).
        register_reason: one line saying why ``register_binning`` was chosen.
        mosaic_reason: one line saying why ``mosaic_binning`` was chosen.
        check_reason: one line saying why ``check_binning`` was chosen.
        agreement_reason: one line saying why ``agreement_binning`` was chosen.
    """

    plan: GroupPlan
    register_binning: int = 1
    check_binning: int | None = None
    agreement_binning: int = 2
    mosaic_binning: int = 1
    register_reason: str = "set in the spec"
    mosaic_reason: str = "set in the spec"
    check_reason: str = "group size set in the spec: pairs are not checked"
    agreement_reason: str = "intensity frames"

    @property
    def group_size(self) -> int:
        """Binary frames per group m at level 1."""
        return self.plan.group_size

    @classmethod
    def for_capture(cls, spec: Any, source: Any) -> Budget:
        """Decide the budget of ``source`` under ``spec`` (``group_size``, ``registration_binning``).

        Args:
            spec: a validated ``PipelineSpec``.
            source: the opened capture (probed for its photon rate and speed, see
                :func:`~photonpano.budget.probe.probe_capture`).

        Raises:
            ValueError: for a ``group_size`` that is neither an integer >= 2 nor ``"auto"``.
            StageError: if ``registration_binning`` or ``mosaic.registration_binning``
                leaves frames smaller than 16 pixels.
        """
        plan = plan_group_size(spec.group_size, source)
        register = registration_binning(spec, source)
        mosaic, mosaic_reason = mosaic_binning(spec, source, register, plan.photons_per_pixel_per_group)
        if spec.registration_binning != "auto":
            register_reason = "set in the spec"
        elif register > 1:
            register_reason = (f"auto: frames of {source.height}x{source.width} keep at least 100 pixels on their "
                               f"short side binned {register}x{register}")
        else:
            register_reason = (f"auto: frames of {source.height}x{source.width} are too small to bin "
                               f"(binned 2x2 they would be below 100 pixels on their short side)")
        check = check_binning(plan, register)
        check_reason = cls.check_reason if check is None else (
            f"group_size auto: level-1 pairs checked on blocks of {max(2, plan.binning)} sensor pixels "
            f"({check} merged-frame pixels)")
        agreement = agreement_binning(plan)
        per_group = plan.photons_per_pixel_per_group
        agreement_reason = cls.agreement_reason if per_group is None else (
            f"{per_group:.3g} photons per pixel per group: blocks of {agreement}x{agreement} gather about 20 "
            "(2 to 8)")
        return cls(plan, register, check, agreement, mosaic, register_reason, mosaic_reason, check_reason,
                   agreement_reason)

    def record(self) -> dict[str, Any]:
        """Return the JSON-ready ``budget`` entry of ``run.json``.

        ``{"group_size", "register_binning", "mosaic_binning", "check_binning",
        "agreement_binning", "reasons": {one line per entry}}``; the plan's details stay in the ``group_size``
        entry (:meth:`~photonpano.budget.probe.GroupPlan.record`).
        """
        return {"group_size": self.group_size, "register_binning": self.register_binning,
                "mosaic_binning": self.mosaic_binning, "check_binning": self.check_binning,
                "agreement_binning": self.agreement_binning,
                "reasons": {"group_size": self.plan.reason, "register_binning": self.register_reason,
                            "mosaic_binning": self.mosaic_reason, "check_binning": self.check_reason,
                            "agreement_binning": self.agreement_reason}}

