"""The evaluation suite: the project's yardstick over many photographs, paths, light levels and nuisances.

Every capture is simulated from one of the real photographs in ``benchmarks/photos/``
(see its ``SOURCES.md``) or the bundled office photo, and reconstructed with the default
``photonpano pano`` settings. Each photograph gets three captures:

1. a base capture: a pan with a 5 px, 30 Hz vibration, 20 000 frames at flux 0.5;
2. a hard one, by turns: zigzag at flux 0.05, random wander (``shake``), a fast pan,
   rotation + zoom, flux 0.005, a dark scene (mean linear intensity 0.016);
3. a nuisance or a length, by turns: hot pixels, a 100 Hz lamp over the whole scene, a
   120 Hz lamp over half of it, a bright moving disc, 6 000 frames, 100 000 frames.

For each capture it prints (and with ``--write``, puts into ``docs/accuracy.md``) the
trajectory RMSE and largest per-frame error after global alignment, the panorama's PSNR
gap to the merge of the same photons with the *true* homographies on the run's own
canvas, how the default compositor compares with ``flux-canvas`` (both with the estimated
homographies; and with ``flux-canvas`` given the true ones), ``status``, the predicted
uncertainty (median sigma, and the share of frames whose
actual error is within twice their sigma), and the wall time; then the suite's aggregate
against the confidence rules of ``docs/outputs.md``:

- every capture whose RMSE exceeds 1 px ends ``degraded`` (or fails with a reason);
- at most 10 % of the captures with RMSE <= 0.3 px are ``degraded``;
- over the ``ok`` captures, 80-98 % of frames are within 2 sigma, and each capture's
  median sigma is within 3x of its RMSE.

``--quick`` runs a small subset (what CI runs, through ``tests/test_suite.py``).
``--stress`` runs the regimes of :data:`STRESS` instead, outside the yardstick: two per
photograph, by turns (docs/accuracy.md, "Regimes outside the suite").

Usage::

    python benchmarks/suite.py                          # every capture (about 25 min on 2 cores)
    python benchmarks/suite.py --quick
    python benchmarks/suite.py --only city_madison,dark --write docs/accuracy.md
    python benchmarks/suite.py --photos other/folder    # the same recipe on other photographs
    python benchmarks/suite.py --stress --photos other/folder
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PHOTOS = HERE / "photos"
VIBRATION = {"vibration_px": 5.0, "vibration_hz": 30.0}

HARD = {
    "zigzag-0.05": {"path": "zigzag", "flux": 0.05, "speed_px_per_frame": 0.02},
    "wander": {"path": "shake", "speed_px_per_frame": 0.005, "shake_px": 8.0},
    "fast-pan": {"speed_px_per_frame": 0.12, "frames": 12_000, "scene_width": 2048},
    "rotation-zoom": {"path": "shake", "rotation_deg": 10.0, "zoom": 0.05, "speed_px_per_frame": 0.005},
    "flux-0.005": {"flux": 0.005},
    "dark": {"mean_intensity": 0.016, "path": "zigzag", "speed_px_per_frame": 0.03},
}
"""Second capture of each photo, assigned by turns: name -> simulate settings over the base."""

NUISANCE = {
    "hot-pixels": {"hot_pixel_fraction": 0.01, "hot_pixel_rate": 0.5},
    "flicker-100": {"flicker_hz": 100.0, "flicker_depth": 0.6, "flicker_region": "all"},
    "flicker-120-half": {"flicker_hz": 120.0, "flicker_depth": 0.9, "flicker_region": "right"},
    "mover": {"mover_radius_px": 30.0, "mover_speed_px_per_frame": 0.08, "mover_intensity": 1.0},
    "short-6000": {"frames": 6_000, "path": "shake", "speed_px_per_frame": 0.02},
    "long-100000": {"frames": 100_000, "speed_px_per_frame": 0.006, "vibration_px": 4.0, "vibration_hz": 45.0},
}
"""Third capture of each photo, assigned by turns: name -> simulate settings over the base."""

STRESS = {
    "reverse-pan": {"speed_px_per_frame": -0.02},
    "tripod-pan": {"pan_model": "rotation"},
    "dark-counts-0.05": {"flux": 0.05, "dark_count_rate": 0.01},
    "big-vibration": {"vibration_px": 15.0, "vibration_hz": 20.0},
    "small-sensor": {"height": 128, "width": 256},
    "bright-zigzag": {"flux": 3.0, "path": "zigzag"},
    "slow-wander-0.05": {"path": "shake", "flux": 0.05, "speed_px_per_frame": 0.005, "shake_px": 4.0},
    "static": {"speed_px_per_frame": 0.0, "vibration_px": 0.0},
    "tall-sensor": {"height": 400, "width": 200},
    "fast-roll": {"rotation_deg": 8.0, "rotation_hz": 5.0},
    "big-zoom": {"zoom": 0.15, "zoom_hz": 1.0},
    "stop-and-go": {"speed_swing": 1.0, "swing_period_frames": 5000},
    "stop-and-go-fast": {"speed_px_per_frame": 0.06, "speed_swing": 1.0, "swing_period_frames": 6000,
                         "frames": 12_000, "scene_width": 2048},
}
"""Regimes no default was chosen on (``--stress``): name -> simulate settings over the base."""

QUICK = ["city_madison/base", "outdoor_camera/dark", "foliage_grass/flux-0.005", "office_equirect/rotation-zoom"]
"""The subset CI runs (one easy, two hard, and rotation + zoom, where the compositor is tested hardest)."""


@dataclass
class Capture:
    """One capture of the suite: a photo and simulate settings."""

    photo: Path
    variant: str
    settings: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        """``photo-stem/variant``."""
        return f"{self.photo.stem}/{self.variant}"

    def source_spec(self) -> dict:
        """The ``source`` section of the capture's spec."""
        return {"plugin": "simulate", "photo": str(self.photo), "frames": 20_000, "flux": 0.5, **VIBRATION,
                **self.settings}


def photos(folder: Path | None = None) -> list[Path]:
    """The suite's photographs: ``folder``'s JPEG/PNG files, or ``benchmarks/photos/`` plus the bundled photo."""
    if folder is not None:
        return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    from photonpano.plugins.sources.simulate import bundled_photo

    return sorted(PHOTOS.glob("*.jpg")) + [bundled_photo()]


def captures(folder: Path | None = None, stress: bool = False) -> list[Capture]:
    """Three captures per photo: the base, a hard one and a nuisance or length, assigned by turns.

    With ``stress``, two of :data:`STRESS` per photo instead, by turns (the i-th photo's
    regimes i and i + 3).
    """
    if stress:
        regimes = list(STRESS.items())
        return [Capture(photo, *regimes[k % len(regimes)]) for i, photo in enumerate(photos(folder))
                for k in (i, i + 3)]
    out = []
    hard, nuisance = list(HARD.items()), list(NUISANCE.items())
    for i, photo in enumerate(photos(folder)):
        out.append(Capture(photo, "base"))
        out.append(Capture(photo, *hard[i % len(hard)]))
        out.append(Capture(photo, *nuisance[i % len(nuisance)]))
    return out


def with_seeds(chosen: list[Capture], seeds: Sequence[int]) -> list[Capture]:
    """Each capture once per photon draw: ``<photo>/<variant>@seed<N>``, the simulator's ``seed`` set to N.

    At flux 0.05 one draw can move a capture's RMSE by half (docs/accuracy.md), so a change
    judged there on one draw is judged on chance.
    """
    return [Capture(c.photo, f"{c.variant}@seed{n}", {**c.settings, "seed": n}) for c in chosen for n in seeds]


def seed_summary(rows: list[dict]) -> list[str]:
    """One line per capture run under several seeds (:func:`with_seeds`): its mean and worst RMSE over them.

    Rows of one capture share the name before ``@seed``; failed runs count as such.
    """
    runs: dict[str, list[dict]] = {}
    for row in rows:
        runs.setdefault(row["capture"].split("@seed")[0], []).append(row)
    lines = []
    for name, group in runs.items():
        rmse = [r["rmse"] for r in group if "failed" not in r]
        failed = len(group) - len(rmse)
        worst = f"worst {max(rmse):.3f}" if rmse else "no run"
        mean = f"mean RMSE {np.mean(rmse):.3f}" if rmse else ""
        lines.append(f"{name:40s} {len(group)} seeds: {mean} {worst}" + (f", {failed} failed" if failed else ""))
    return lines


def run_capture(capture: Capture, dump: Path | None = None, overrides: Sequence[str] = ()) -> dict:
    """Simulate and reconstruct one capture with the default settings; return its row.

    ``overrides`` are ``--set``-style spec changes (``"level_schemes=[pairwise]"``), for
    judging a candidate default on the whole suite against the current one.

    With ``dump``, the per-frame actual error and predicted sigma go to
    ``dump/<photo>--<variant>.npz`` (``error``, ``sigma``, ``unverified``, ``shape`` (the
    uncertainty's shape term, zero without it) per frame, the
    final ``homographies``, ``width`` and ``height``, the last level's evidence pairs
    ``middle``, ``residual``, ``ok``, and level 1's as ``first_middle``, ``first_residual``,
    ``first_ok``, and every level's ``level_homographies`` (L, T, 3, 3) and per-frame
    ``level_errors`` (L, T); for recalibrating offline).
    """
    from photonpano.host import PluginHost
    from photonpano.metrics import ground_truth_report, source_trajectory_error
    from photonpano.pipeline import reconstruct
    from photonpano.plugins.compositors.flux_canvas import FluxCanvasConfig
    from photonpano.spec import apply_overrides, validate_spec
    from photonpano.uncertainty import held_out_residuals

    row: dict = {"capture": capture.name, "frames": capture.source_spec()["frames"]}
    try:
        data = apply_overrides({"source": capture.source_spec()}, list(overrides))
        spec = validate_spec(data, PluginHost(), origin=capture.name)
        source = spec.source.build()
    except Exception as exc:  # noqa: BLE001 - a capture the simulator refuses is a row too
        return {**row, "failed": f"simulate: {str(exc).splitlines()[0]}"}
    report: dict = {}
    levels: list = []
    t0 = time.perf_counter()
    try:
        homographies, stats, pano, timings = reconstruct(spec, source, report=report, on_level=levels.append)
    except Exception as exc:  # noqa: BLE001 - a failed run is a row too (it must fail with a reason)
        return {**row, "failed": str(exc).splitlines()[0], "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    gt = ground_truth_report(source, homographies, pano, spec.panorama_subbatch_px, compositor=spec.compositor,
                             references=(FluxCanvasConfig(scale=spec.compositor.scale),), references_estimated=True,
                             flicker_period_frames=(report.get("flicker") or {}).get("period_frames"))
    error = source_trajectory_error(homographies, source).per_frame_px
    unc = report.get("frame_uncertainty")
    sigma = unc.sigma_px if unc is not None else np.full(len(error), np.nan)
    if dump is not None:
        dump.mkdir(parents=True, exist_ok=True)
        evidence = held_out_residuals(levels[-1], source.width, source.height)
        pairs = dict(zip(("middle", "residual", "ok"), evidence[1:4])) if evidence is not None else {}
        first = held_out_residuals(levels[0], source.width, source.height) if len(levels) > 1 else None
        if first is not None:
            pairs.update(zip(("first_middle", "first_residual", "first_ok"), first[1:4]))
        unverified = unc.unverified if unc is not None else np.zeros(len(error), bool)
        shape = unc.shape_px if unc is not None and unc.shape_px is not None else np.zeros(len(error))
        np.savez(dump / f"{capture.name.replace('/', '--')}.npz", error=error, sigma=sigma, unverified=unverified,
                 shape=shape, homographies=homographies, width=source.width, height=source.height,
                 level_homographies=np.stack([level.homographies for level in levels]),
                 level_errors=np.stack([source_trajectory_error(level.homographies, source).per_frame_px
                                        for level in levels]), **pairs)
    return {**row, "rmse": gt["trajectory_rmse_px"], "max": gt["trajectory_max_px"], "psnr_gap": gt["psnr_gap_db"],
            "over_flux_canvas": gt["psnr_db"] - gt["psnr_estimated_by"]["flux-canvas"],
            "over_flux_canvas_true": gt["psnr_db"] - gt["psnr_true_homographies_by"]["flux-canvas"],
            "status": report["status"], "warnings": report["warnings"],
            "sigma_median": float(np.median(sigma)), "within_2_sigma": float(np.mean(error <= 2 * sigma)),
            "seconds": seconds, "confidence_s": timings.get("confidence", 0.0),
            "levels": [{"scheme": st["scheme"], "rmse": st.get("trajectory_rmse_px"),
                        "failed_fraction": st.get("quality", {}).get("failed_fraction"),
                        "residual_px": st.get("quality", {}).get("pose_graph_residual_px"),
                        "movers": st.get("movers"), "registration_check": st.get("registration_check")}
                       for st in stats]}


def aggregate(rows: list[dict]) -> dict:
    """The suite's verdict on the confidence rules (see the module)."""
    done = [r for r in rows if "failed" not in r]
    bad = [r for r in done if r["rmse"] > 1.0]
    good = [r for r in done if r["rmse"] <= 0.3]
    ok = [r for r in done if r["status"] == "ok"]
    frames = sum(r["frames"] for r in ok)
    within = sum(r["within_2_sigma"] * r["frames"] for r in ok) / frames if frames else float("nan")
    ratios = [r["sigma_median"] / max(r["rmse"], 1e-9) for r in ok]
    return {
        "captures": len(rows), "failed": len(rows) - len(done),
        "rmse_over_1px": len(bad), "rmse_over_1px_not_degraded": [r["capture"] for r in bad if r["status"] == "ok"],
        "rmse_under_0.3px": len(good), "rmse_under_0.3px_degraded": [r["capture"] for r in good
                                                                    if r["status"] != "ok"],
        "ok_frames_within_2_sigma": within,
        "ok_sigma_over_rmse": [float(np.min(ratios)), float(np.median(ratios)), float(np.max(ratios))]
        if ratios else None,
        "ok_sigma_not_within_3x": [r["capture"] for r, q in zip(ok, ratios) if not 1 / 3 <= q <= 3],
        "compositor_below_flux_canvas": [r["capture"] for r in done if r["over_flux_canvas"] < -0.05],
        "compositor_below_true_bilinear": [r["capture"] for r in done if r["over_flux_canvas_true"] < -0.2],
    }


def verdict(summary: dict) -> list[str]:
    """The confidence rules the suite's aggregate breaks (empty: all hold)."""
    broken = []
    if summary["rmse_over_1px_not_degraded"]:
        broken.append(f"RMSE > 1 px but ok: {summary['rmse_over_1px_not_degraded']}")
    if len(summary["rmse_under_0.3px_degraded"]) > 0.1 * max(summary["rmse_under_0.3px"], 1):
        broken.append(f"more than 10 % of the RMSE <= 0.3 px captures degraded: "
                      f"{summary['rmse_under_0.3px_degraded']}")
    within = summary["ok_frames_within_2_sigma"]
    if np.isfinite(within) and not 0.80 <= within <= 0.98:
        broken.append(f"{within:.1%} of the ok captures' frames within 2 sigma (80-98 % wanted)")
    if summary["ok_sigma_not_within_3x"]:
        broken.append(f"median sigma not within 3x of the RMSE: {summary['ok_sigma_not_within_3x']}")
    return broken


def markdown(rows: list[dict], summary: dict) -> str:
    """The rows and the aggregate as Markdown."""
    lines = ["| capture | frames | RMSE (px) | max (px) | PSNR gap (dB) | over flux-canvas (dB) "
             "| over true bilinear (dB) | status | median sigma (px) | frames within 2 sigma | wall (s) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "failed" in r:
            lines.append(f"| {r['capture']} | {r['frames']} | failed: {r['failed']} | | | | | error | | | |")
            continue
        lines.append(f"| {r['capture']} | {r['frames']} | {r['rmse']:.3f} | {r['max']:.2f} | {r['psnr_gap']:.2f} "
                     f"| {r['over_flux_canvas']:+.2f} | {r['over_flux_canvas_true']:+.2f} | {r['status']} "
                     f"| {r['sigma_median']:.3f} | {r['within_2_sigma']:.0%} | {r['seconds']:.1f} |")
    s = summary
    ratio = s["ok_sigma_over_rmse"]
    lines += ["", f"{s['captures']} captures, {s['failed']} failed. RMSE > 1 px: {s['rmse_over_1px']}, of them "
              f"not degraded: {len(s['rmse_over_1px_not_degraded'])}. RMSE <= 0.3 px: {s['rmse_under_0.3px']}, "
              f"of them degraded: {len(s['rmse_under_0.3px_degraded'])}. Frames of ok captures within 2 sigma: "
              f"{s['ok_frames_within_2_sigma']:.1%}; median sigma / RMSE over ok captures: "
              + (f"{ratio[0]:.2f} to {ratio[2]:.2f} (median {ratio[1]:.2f})." if ratio else "none.")]
    lines.append(f"Default compositor below flux-canvas by more than 0.05 dB (same estimated motion): "
                 f"{len(s['compositor_below_flux_canvas'])} {s['compositor_below_flux_canvas'] or ''}; below the "
                 f"bilinear merge with the true motion by more than 0.2 dB: {len(s['compositor_below_true_bilinear'])} "
                 f"{s['compositor_below_true_bilinear'] or ''}.")
    broken = verdict(summary)
    lines.append("Every confidence rule holds." if not broken else "Rules broken: " + "; ".join(broken) + ".")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the suite (or a part), print the table and aggregate; exit 1 when a confidence rule breaks."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    parser.add_argument("--stress", action="store_true", help=f"the regimes outside the suite: {', '.join(STRESS)}")
    parser.add_argument("--only", default="", help="comma-separated substrings of capture names to run")
    parser.add_argument("--photos", type=Path, help="a folder of other photographs to run the same recipe on")
    parser.add_argument("--list", action="store_true", help="list the captures and exit")
    parser.add_argument("--json", type=Path, help="also write the rows and aggregate to this JSON file")
    parser.add_argument("--dump", type=Path, help="save each capture's per-frame error and sigma here (.npz)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a spec override for every capture, as `photonpano run --set` (repeatable)")
    parser.add_argument("--seeds", default="", help="comma-separated photon draws: each capture runs once per "
                        "simulator seed (named <capture>@seed<N>), then its mean and worst RMSE over them")
    parser.add_argument("--write", type=Path, help="put the table into this Markdown file between "
                        "<!-- suite-table:start --> and <!-- suite-table:end -->")
    args = parser.parse_args(argv)
    chosen = captures(args.photos, args.stress)
    if args.quick:
        chosen = [c for c in chosen if c.name in QUICK]
    if args.only:
        keys = args.only.split(",")
        chosen = [c for c in chosen if any(k in c.name for k in keys)]
    if args.seeds:
        try:
            seeds = [int(n) for n in args.seeds.split(",")]
        except ValueError:
            parser.error(f"--seeds {args.seeds!r}: expected comma-separated whole numbers, e.g. 0,1,2")
        chosen = with_seeds(chosen, seeds)
    if args.list:
        for c in chosen:
            print(c.name, json.dumps(c.settings))
        return 0
    rows = []
    for capture in chosen:
        row = run_capture(capture, args.dump, args.set)
        rows.append(row)
        if "failed" in row:
            print(f"{row['capture']:40s} failed: {row['failed']}", flush=True)
        else:
            print(f"{row['capture']:40s} RMSE {row['rmse']:7.3f} max {row['max']:7.2f} gap {row['psnr_gap']:5.2f} dB "
                  f"fc {row['over_flux_canvas']:+5.2f}/{row['over_flux_canvas_true']:+5.2f} dB "
                  f"{row['status']:8s} sigma {row['sigma_median']:6.3f} within-2s {row['within_2_sigma']:4.0%} "
                  f"{row['seconds']:5.1f} s", flush=True)
    summary = aggregate(rows)
    table = markdown(rows, summary)
    print()
    print(table)
    if args.seeds:
        print()
        print("\n".join(seed_summary(rows)))
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "aggregate": summary}, indent=1))
    if args.write:
        sys.path.insert(0, str(HERE))
        from accuracy import write_table

        command = "python benchmarks/suite.py" + (" --quick" if args.quick else "")
        write_table(args.write, table, command, name="suite-table", legend="")
    return 1 if verdict(summary) else 0


if __name__ == "__main__":
    sys.exit(main())
