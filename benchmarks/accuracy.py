"""Accuracy benchmark (issues 2 and 11): trajectory error and panorama PSNR against ground truth.

Simulates captures from a real photo (254x496 frames at 100 kHz, default: the bundled
one) in several regimes and reconstructs each with variants of the pipeline:

- ``acceptance-0.5`` / ``acceptance-0.05``: the issue-2 capture, a horizontal pan of
  0.02 px/frame plus a 5 px, 30 Hz circular vibration, 20 000 frames at flux 0.5 / 0.05;
- ``fast-pan``: 0.12 px/frame plus the vibration, 12 000 frames, flux 0.5 (the frame
  crosses its own width in about 40 ms);
- ``dark-flux``: the acceptance path at flux 0.005 (100x less light than the demo);
- ``dark-scene``: the photo darkened to a mean linear intensity of 0.016, flux 0.5,
  zigzag path at 0.03 px/frame plus the vibration;
- ``rotation-zoom``: a random shake path with a 10 degree rotation and a 5 % zoom
  oscillation at flux 0.5.

Variants: ``default`` (``photonpano pano``'s settings, ``group_size: auto``), ``m500``
(the former default, m = 500), ``paper`` (the paper's plain settings at m = 500) and
``level1`` (level 1 of the default spec only).

With ``--write``, the table replaces the one between ``<!-- accuracy-table:start -->``
and ``<!-- accuracy-table:end -->`` in that Markdown file (``docs/accuracy.md``; another
name than ``accuracy-table`` with ``--table``), so the documentation shows what the
benchmark measured.

Usage::

    python benchmarks/accuracy.py --write docs/accuracy.md        # every regime, default spec
    python benchmarks/accuracy.py --regimes fast-pan --frames 6000 --variants default,m500
    python benchmarks/accuracy.py --photo other.jpg --regimes dark-scene
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

from photonpano.host import PluginHost
from photonpano.metrics import ground_truth_report
from photonpano.pipeline import reconstruct
from photonpano.spec import apply_overrides, validate_spec

VIBRATION = {"vibration_px": 5.0, "vibration_hz": 30.0}
REGIMES: dict[str, tuple[dict, float]] = {
    "acceptance-0.5": ({"frames": 20_000, "flux": 0.5, **VIBRATION}, 0.3),
    "acceptance-0.05": ({"frames": 20_000, "flux": 0.05, **VIBRATION}, 0.6),
    "fast-pan": ({"frames": 12_000, "flux": 0.5, "speed_px_per_frame": 0.12, "scene_width": 2048,
                  **VIBRATION}, 0.5),
    "dark-flux": ({"frames": 20_000, "flux": 0.005, **VIBRATION}, 1.0),
    "dark-scene": ({"frames": 20_000, "flux": 0.5, "mean_intensity": 0.016, "path": "zigzag",
                    "speed_px_per_frame": 0.03, **VIBRATION}, 0.5),
    "rotation-zoom": ({"frames": 20_000, "flux": 0.5, "path": "shake", "rotation_deg": 10.0, "zoom": 0.05,
                       **VIBRATION}, 0.3),
}
"""Regime -> (simulate settings, acceptance bar on the final trajectory RMSE in px)."""

VARIANTS = {
    "default": [],
    "m500": ["group_size=500"],
    "paper": ["group_size=500", "pair_offsets=[1]", "locator.refine=lm",
              "interpolator.measurement=reference-frame", "resampler.anchor_ends=false"],
    "level1": ["levels=1"],
}
START, END = "<!-- {}:start -->", "<!-- {}:end -->"


def run_case(regime: str, variant: str, frames: int | None, photo: Path | None, host: PluginHost,
             sources: dict) -> dict:
    """Simulate (once per regime) and reconstruct one case; return its table row."""
    settings, bar = REGIMES[regime]
    source_spec = {"plugin": "simulate", **settings}
    if frames:
        source_spec["frames"] = frames
    if photo:
        source_spec["photo"] = str(photo)
    spec = validate_spec(apply_overrides({"source": source_spec}, VARIANTS[variant]), host, origin=variant)
    if regime not in sources:
        sources.clear()  # one capture in memory at a time
        sources[regime] = spec.source.build()
    source = sources[regime]
    report: dict = {}
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    try:
        homographies, stats, pano, _ = reconstruct(spec, source, report=report)
    except Exception as exc:  # a failed run is a row too
        return {"regime": regime, "variant": variant, "frames": source.n_frames, "bar": bar,
                "failed": str(exc).splitlines()[0]}
    seconds, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    gt = ground_truth_report(source, homographies, pano, spec.panorama_subbatch_px, compositor=spec.compositor)
    plan = report["group_size"]
    return {"regime": regime, "variant": variant, "frames": source.n_frames, "bar": bar,
            "rmse": [row["trajectory_rmse_px"] for row in stats], "psnr": gt["psnr_db"],
            "psnr_true": gt["psnr_true_homographies_db"], "gap": gt["psnr_gap_db"],
            "group_size": plan["group_size"], "binning": plan["binning"], "status": report["status"],
            "warnings": report["warnings"], "seconds": seconds, "cpu_s": cpu}


def markdown(rows: list[dict]) -> str:
    """Return the rows as a Markdown table."""
    lines = ["| regime | frames | variant | RMSE per level (px) | bar (px) | PSNR (dB) | true-H PSNR (dB) "
             "| gap (dB) | m (binning) | status | wall (CPU) s |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "failed" in r:
            lines.append(f"| {r['regime']} | {r['frames']} | {r['variant']} | failed: {r['failed']} "
                         f"| {r['bar']} | | | | | error | |")
            continue
        rmse = ", ".join(f"{v:.3f}" for v in r["rmse"])
        mark = "**" if r["rmse"][-1] <= r["bar"] else ""
        lines.append(f"| {r['regime']} | {r['frames']} | {r['variant']} | {rmse[:-5]}{mark}{rmse[-5:]}{mark} "
                     f"| {r['bar']} | {r['psnr']:.2f} | {r['psnr_true']:.2f} | {r['gap']:.2f} "
                     f"| {r['group_size']} ({r['binning']}) | {r['status']} "
                     f"| {r['seconds']:.0f} ({r['cpu_s']:.0f}) |")
    return "\n".join(lines)


def portable_command(command: str, root: Path = Path(__file__).resolve().parents[1]) -> str:
    """``command`` with no path of this machine in it, for the docs' stamps.

    An absolute path inside the repository ``root`` becomes relative to it; any other
    (``--photo /data/photos/x.png``, ``--write=/tmp/doc.md``) keeps only its file name.
    Other words are kept.
    """
    def portable(word: str) -> str:
        option, eq, value = word.rpartition("=") if word.startswith("-") and "=" in word else ("", "", word)
        path = Path(value)
        if not path.is_absolute():
            return word
        try:
            value = str(path.resolve().relative_to(root))
        except ValueError:
            value = path.name
        return f"{option}{eq}{value}"

    return " ".join(portable(word) for word in command.split(" "))


def write_table(path: Path, table: str, command: str, name: str = "accuracy-table",
                legend: str = ", bold: meets the bar") -> None:
    """Replace the text between the markers ``<!-- name:start -->`` and ``<!-- name:end -->`` of ``path``.

    Raises:
        SystemExit: if the file lacks the markers.
    """
    start, end = START.format(name), END.format(name)
    text = path.read_text()
    if start not in text or end not in text:
        raise SystemExit(f"{path}: no {start} ... {end} markers to write the table between")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    stamp = (f"Written by `{portable_command(command)}` on {time.strftime('%Y-%m-%d')} "
             f"({platform.node() or 'this machine'}{legend}).")
    path.write_text(f"{head}{start}\n{stamp}\n\n{table}\n{end}{tail}")


def main() -> None:
    """Run the benchmark, print a Markdown table, and optionally write it into a document."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--regimes", default=",".join(REGIMES),
                        help=f"comma-separated, of {', '.join(REGIMES)}")
    parser.add_argument("--variants", default="default", help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--frames", type=int, default=None, help="override every regime's frame count")
    parser.add_argument("--photo", type=Path, default=None, help="photo to simulate from (default: bundled)")
    parser.add_argument("--write", type=Path, default=None, help="Markdown file whose table to replace")
    parser.add_argument("--table", default="accuracy-table", help="marker name of the table to replace")
    args = parser.parse_args()
    host = PluginHost()
    rows, sources = [], {}
    for regime in args.regimes.split(","):
        for variant in args.variants.split(","):
            rows.append(run_case(regime, variant, args.frames, args.photo, host, sources))
            print(markdown(rows[-1:]).splitlines()[-1], flush=True)
    table = markdown(rows)
    print(table)
    if args.write:
        import sys

        write_table(args.write, table, "python benchmarks/accuracy.py " + " ".join(sys.argv[1:]), args.table)


if __name__ == "__main__":
    main()
