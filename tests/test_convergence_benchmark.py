"""benchmarks/convergence.py: smooth trajectory errors injected into the truth, and measured back."""

import numpy as np
import pytest
from capture_helpers import load_benchmark


def _module():
    return load_benchmark("convergence")


@pytest.mark.parametrize("mode, end_px", [("shift", 0.4), ("xscale", 0.4), ("rotation", 0.4), ("rotation-bump", 0.0),
                                          ("step", 0.4), ("perspective", 0.4), ("vertical-perspective", 0.4)])
def test_each_mode_moves_the_frame_by_its_amplitude_at_the_ends_of_the_capture(mode, end_px):
    """At the last frame a mode of amplitude A moves the frame's centre (shift), edges (stretch) or corners by A px."""
    from photonpano import geometry

    convergence = _module()
    w, h = 496, 254
    steps = np.linspace(-1, 1, 101)
    params = convergence.mode_params(mode, steps, 0.4, w, h)
    last = geometry.from_centre(geometry.homographies_from_params(params[-1:]), w, h)[0]
    centre, edge = [((w - 1) / 2, (h - 1) / 2)], [(w - 1, (h - 1) / 2), (0, (h - 1) / 2)]
    points = {"shift": centre, "step": centre, "xscale": edge, "perspective": edge}.get(mode, geometry.corners(w, h))
    moved = geometry.apply(last, np.asarray(points, np.float64)) - np.asarray(points)
    # the vertical keystone moves the corners sideways by A (and up or down by A h / w)
    moved = np.abs(moved[:, 0]) if mode == "vertical-perspective" else np.linalg.norm(moved, axis=-1)
    assert np.allclose(moved, end_px, atol=2e-3)
    # the projection recovers the amplitude of a mode buried in another mode's error
    other = convergence.mode_params("xscale" if mode in ("shift", "step") else "shift", steps, 0.3, w, h)
    unit = convergence.mode_params(mode, steps, 1.0, w, h)
    assert convergence.mode_amplitude(params + other, unit) == pytest.approx(0.4, abs=1e-9)
    with pytest.raises(ValueError, match="expected one of"):
        convergence.mode_params("twist", steps, 0.4, w, h)
