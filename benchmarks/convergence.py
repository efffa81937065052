"""How fast the refining levels remove each kind of trajectory error: an error injected into the truth.

Starts the levels after level 1 (the default ``mosaic`` levels) from the *true* trajectory
of an evaluation-suite capture with one smooth error added, the kind of error level 1
leaves, and prints what is left of it after each level:

- ``shift``: the frame centre off by a ramp along the pan, ``-A`` px at the first frame to
  ``+A`` at the last;
- ``xscale``: the frames stretched horizontally by a ramp, ``A`` px at the frame's left and
  right edges at the ends of the capture;
- ``rotation``: the frames turned about their centres by a ramp, ``A`` px at the frame
  corners at the ends of the capture (a panorama bent like a banana along the pan);
- ``rotation-bump``: the same turn rising and falling once, ``A sin(pi s)``, ``s`` from -1
  to 1 over the capture;
- ``step``: the frame centre off by ``-A`` px over the first half of the capture and ``+A``
  over the second (a wrong link in level 1's chain);
- ``perspective``: the frames' horizontal keystone (``p7``) by a ramp, ``A`` px at the
  frame's left and right edges at the ends of the capture;
- ``vertical-perspective``: the frames' vertical keystone (``p8``) by a ramp, ``A`` px at
  the frame corners (horizontally) at the ends of the capture.

With ``--amplitude 0`` the levels start from the truth itself (one run for every mode), and
each mode's column is the amplitude the levels *put in*, in px (what their registrations'
noise and bias leave in that mode).

Frame-to-mosaic registration measures each frame against a panorama made with the same
erroneous estimate; an error the frames that see the same canvas share is partly in the
panorama too (:mod:`photonpano.schemes.template_bias`), and an error that bends the whole
panorama smoothly is consistent with it almost everywhere. For each level the script
prints the trajectory RMSE after the best global alignment and the injected mode's
amplitude in the result (its projection, in px at the frame corner: 1.0 means untouched,
0 removed), for the final trajectory and for the level's registrations (keyframes,
before interpolation).

Measured 2026-11-26 (amplitude 0.4 px, base captures; RMSE after levels 2 and 3, and the
share of the mode left after them): on the facade (``--photo facade_brick``) the shift
ramp 0.193 -> 0.034 -> 0.031 px (0.04 left) and the stretch 0.122 -> 0.028 -> 0.025 px
(0.00) go in one level, the turn does not: 0.226 -> 0.108 -> 0.087 px (0.23, then 0.19
left; with ``levels=6`` 0.17, 0.16, 0.14: about a tenth of what is left per level). Its
registrations see the turn about three quarters of it, after the template-bias
correction. ``level_schemes=[pairwise,pairwise,mosaic]`` overshoots it at level 2 (-0.15,
0.274 px) and ends at 0.053 px. A disc crossing the facade leaves such a turn after level
1 (0.27 px at the capture's start after three levels, docs/real_scenes.md). On the gravel
at flux 0.05 (``--photo texture_gravel --set source.flux=0.05``) all three go in one
level (0.036-0.040 px), while the real capture ends at 0.148 px after level 1's 0.30:
what level 1 leaves there is none of these ramps. A keystone ramp of 0.6 px on the
astronaut (``--photo portrait_astronaut --mode perspective --amplitude 0.6``): 0.347 ->
0.188 -> 0.173 px (0.59, then 0.53 left); with ``--set
mosaic.template_bias_priors=per-parameter`` 0.059 -> 0.055 px (0.18, then 0.16 left), and
the facade's turn above 0.030 -> 0.025 px (0.05, then 0.03 left).

Measured 2026-11-27 (the sunset at flux 0.05, ``--photo highcontrast_sunset --set
source.flux=0.05``): from the truth itself (``--amplitude 0``) levels 2 and 3 end at 0.077
and 0.109 px, putting in a vertical keystone ramp of 0.051 then 0.097 px and a horizontal
one of -0.037 then -0.086 (handwriting 0.093 and 0.110 px, coffee 0.067 and 0.090, the
gravel 0.036 and 0.036 with no ramp); of a vertical keystone ramp of 0.4 px
(``--mode vertical-perspective``) 0.74 is left after the two levels, against 0.19 at flux
0.5, where from the truth they end at 0.029 and 0.031 px (``p8`` -0.009 then -0.017). See
docs/accuracy.md ("Where the two flux-0.05 misses' error is").

Usage::

    python benchmarks/convergence.py --photo facade_brick
    python benchmarks/convergence.py --photo texture_gravel --mode rotation --amplitude 0.8 --set levels=5
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

MODES = ("shift", "xscale", "rotation", "rotation-bump", "step", "perspective", "vertical-perspective")


def mode_params(mode: str, steps: np.ndarray, amplitude: float, width: int, height: int) -> np.ndarray:
    """(T, 8) parameters p1..p8 about the frame centre of ``mode`` at ``steps`` in [-1, 1] (see the module).

    Raises:
        ValueError: for a mode not in :data:`MODES`.
    """
    params = np.zeros((len(steps), 8))
    corner = np.hypot(width - 1, height - 1) / 2
    if mode == "shift":
        params[:, 4] = amplitude * steps
    elif mode == "step":
        params[:, 4] = amplitude * np.sign(steps)
    elif mode == "perspective":
        params[:, 6] = amplitude / ((width - 1) / 2) ** 2 * steps  # x' = x - p7 x^2 about the centre
    elif mode == "vertical-perspective":
        params[:, 7] = amplitude / ((width - 1) / 2 * (height - 1) / 2) * steps  # x' = x - p8 x y about the centre
    elif mode == "xscale":
        params[:, 0] = amplitude / ((width - 1) / 2) * steps
    elif mode in ("rotation", "rotation-bump"):
        turn = amplitude / corner * (steps if mode == "rotation" else np.sin(np.pi * steps))
        params[:, 1], params[:, 2] = turn, -turn  # small angles: [[1, -a], [a, 1]]
    else:
        raise ValueError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    return params


def mode_amplitude(errors: np.ndarray, unit: np.ndarray) -> float:
    """Least-squares amplitude of the (T, 8) mode ``unit`` (amplitude 1) in the (T, 8) parameter errors."""
    return float(np.sum(errors * unit) / max(np.sum(unit * unit), 1e-30))


def main(argv: list[str] | None = None) -> int:
    """Inject the mode, run the refining levels from it and print what is left after each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photo", default="facade_brick",
                        help="an evaluation-suite photo's stem, or the path of another photograph")
    parser.add_argument("--variant", default="base", help="the suite capture of the photo (base, mover, ...)")
    parser.add_argument("--mode", default=",".join(MODES[:3]), help=f"comma-separated: {', '.join(MODES)}")
    parser.add_argument("--amplitude", type=float, default=0.4, help="px at the frame corner or edge")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="spec override")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).parent))
    import suite
    from photonpano import geometry
    from photonpano.executor import make_executor
    from photonpano.host import PluginHost
    from photonpano.metrics import source_trajectory_error, trajectory_error
    from photonpano.outputs import Checkpoint
    from photonpano.reconstruction import Stages
    from photonpano.spec import apply_overrides, validate_spec

    settings = {**suite.HARD, **suite.NUISANCE}.get(args.variant, {})
    photo = Path(args.photo) if Path(args.photo).suffix else suite.PHOTOS / f"{args.photo}.jpg"
    capture = suite.Capture(photo, args.variant, settings)
    if not capture.photo.exists():
        parser.error(f"--photo {args.photo}: no {capture.photo}")
    spec = validate_spec(apply_overrides({"source": capture.source_spec()}, args.set), PluginHost(),
                         origin=capture.name)
    source = spec.source.build()
    truth_to_scene = source.ground_truth
    n, w, h = len(truth_to_scene), source.width, source.height
    truth = geometry.normalize(np.linalg.inv(truth_to_scene[n // 2]) @ truth_to_scene)
    steps = np.linspace(-1.0, 1.0, n)

    def mode_error(homographies: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """(K, 8) parameters about the centre of frames' errors against the truth, after the best global alignment."""
        aligned = trajectory_error(homographies, truth_to_scene[frames], w, h).alignment @ homographies
        return geometry.params_from_homographies(geometry.about_centre(
            np.linalg.inv(truth_to_scene[frames]) @ aligned, w, h))

    left = ("mode left in the trajectory / in the registrations (1: untouched)" if args.amplitude else
            "mode put in the trajectory / in the registrations (px)")
    scale, digits = (args.amplitude, 2) if args.amplitude else (1.0, 3)  # from the truth: px put in
    print(f"{capture.name}, {n} frames, amplitude {args.amplitude} px; per level: RMSE (px), {left}")
    modes = [m.strip() for m in args.mode.split(",") if m.strip()]
    units = {mode: mode_params(mode, steps, 1.0, w, h) for mode in modes}
    # each mode injected in a run of its own; from the truth, one run shows every mode
    runs = [(mode, (mode,)) for mode in modes] if args.amplitude else [(modes[0], tuple(modes))]
    for injected_mode, shown in runs:
        injected = geometry.from_centre(geometry.homographies_from_params(args.amplitude * units[injected_mode]), w, h)
        start = geometry.normalize(truth @ injected)
        start_px = source_trajectory_error(start, source).rmse_px
        rows = {mode: [f"  {mode}: start {start_px:.3f} px"] for mode in shown}

        def level_done(result, shown=shown, rows=rows) -> None:
            error = source_trajectory_error(result.homographies, source)
            reference = result.groups.reference
            trajectory, registered = mode_error(result.homographies, np.arange(n)), mode_error(
                result.located.keyframes, reference)
            for mode in shown:
                everywhere = mode_amplitude(trajectory, units[mode]) / scale
                measured = mode_amplitude(registered, units[mode][reference]) / scale
                rows[mode].append(f"level {result.level} {error.rmse_px:.3f} px, "
                                  f"{everywhere:.{digits}f} / {measured:.{digits}f}")

        with make_executor(spec.executor, spec.workers, spec.dask_address) as executor:
            Stages(spec, source).estimate_motion(executor, on_level=level_done,
                                                 resume=Checkpoint(1, start, []))
        for mode in shown:
            print("; ".join(rows[mode]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
