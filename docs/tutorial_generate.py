"""Generate the numbers, command outputs and pictures of docs/tutorial.md from real runs of the tool.

Runs exactly the tutorial's commands in a scratch folder:

1. ``photonpano demo`` with ``source.cube_path`` set, so the simulated photon cube is
   also written as a bit-packed ``.npy`` file;
2. ``photonpano pano`` on that cube with every level's merged frames dumped (the
   paper's pairwise registration at every level, ``level_schemes: [pairwise]``);

then measures the page's figures (:data:`FIGURES`) and makes its pictures (small 8-bit
PNGs: one binary frame of the cube, the virtual exposure around the middle frame at
level 1 and at the last level, the demo's ``trajectory.png`` and its panorama; each
under 300 KB).

In the page, a figure is written ``0.128<!--binary_mean-->`` (the comment names it; it
does not render) and a command's output is the fenced ``text`` block after a line
``<!--output:demo-->`` or ``<!--output:pano-->``. By default the script rewrites those
and ``docs/img/``; with ``--check`` it changes nothing and exits 1, listing every figure
that drifted beyond its tolerance, every output line whose words or numbers changed
(timings, numbers followed by `` s``, are not compared; nor blank lines and the order in
which stdout and stderr interleave) and every picture that no longer
matches (another size, or a mean difference above :data:`PICTURE_TOLERANCE` grey levels).
``tests/test_tutorial.py`` runs the check.

Usage (from the repository root, about a minute on two cores)::

    python docs/tutorial_generate.py [--check] [--work SCRATCH_FOLDER]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

DOCS = Path(__file__).parent
PAGE = DOCS / "tutorial.md"
IMG = DOCS / "img"
MAX_BYTES = 300_000
"""Largest PNG written (bytes), to keep the repository small."""
PANORAMA_WIDTH = 960
"""Wider panoramas are shrunk to this width (pixels) for the page."""
PICTURE_TOLERANCE = 6.0
"""Largest mean absolute difference (8-bit grey levels) between a regenerated picture and the page's."""
OUTPUT_TOLERANCE = (0.05, 0.02)
"""Numbers in a command's output may drift by 5 % of their value or 0.02, whichever is larger."""
SIGMA_TOLERANCE = (0.35, 0.02)
"""The same for the predicted per-frame error (``predicted per-frame error ...`` lines): a
sigma is a prediction the confidence rules hold to within 3x of the error, and the
pairwise run's (pose-graph evidence) follows the CPU's floating-point path through SIFT:
its median 0.174 px on the machine that wrote the page before 2026-11-26, 0.133 px on a
2-core AMD EPYC machine, every other number of the page within tolerance."""

FIGURES: dict[str, tuple[str, float, str]] = {
    "binary_mean": ("{:.3f}", 0.005, "fraction of pixels that saw a photon in the middle binary frame"),
    "group_size": ("{:d}", 0, "group size (binary frames) chosen by group_size: auto"),
    "group_ms": ("{:.1f}", 0.0, "duration of one group in milliseconds"),
    "group_reference": ("{:d}", 0, "centre frame of the level-1 group nearest the middle frame"),
    "group_pan_px": ("{:.0f}", 0.5, "how far the camera panned during one group (px)"),
    "inliers_level_1": ("{:.0f}", 10, "median SIFT inliers of the level-1 pairs"),
    "rmse_level_1": ("{:.2f}", 0.03, "trajectory RMSE against the truth after level 1 (px)"),
    "rmse_final": ("{:.3f}", 0.02, "trajectory RMSE against the truth after the last level (px)"),
    "max_final": ("{:.2f}", 0.05, "worst per-frame error after the last level (px)"),
    "h_tx": ("{:.1f}", 0.5, "x translation of the middle frame's homography (canvas px)"),
    "h_ty": ("{:.2f}", 0.5, "y translation of the middle frame's homography (canvas px)"),
    "psnr": ("{:.2f}", 0.3, "panorama PSNR against the true scene (dB)"),
    "psnr_true": ("{:.2f}", 0.3, "PSNR with the true homographies (dB)"),
    "psnr_gap": ("{:.2f}", 0.15, "PSNR lost to the motion error (dB)"),
    "canvas_width": ("{:d}", 4, "panorama canvas width (px)"),
    "canvas_height": ("{:d}", 4, "panorama canvas height (px)"),
}
"""Each figure of the page: its format, the largest drift allowed (absolute, in its unit) and what it is."""

COMMANDS = {
    "demo": ["demo", "-o", "demo-out", "--set", "source.cube_path=capture.npy"],
    "pano": ["pano", "capture.npy", "-o", "levels-out", "--set", "outputs.merged_frames=true",
             "--set", "level_schemes=[pairwise]"],
}
"""The tutorial's commands (run in the scratch folder, so outputs name relative paths)."""

FIGURE = re.compile(r"(-?\d+(?:\.\d+)?)<!--(\w+)-->")
OUTPUT = re.compile(r"(<!--output:(\w+)-->\n```text\n)(.*?)(```)", re.S)
NUMBER = re.compile(r"(\d+(?:\.\d+)?)")


def photonpano(work: Path, *args: str) -> str:
    """Run the ``photonpano`` CLI of this interpreter in ``work``; return its output lines without progress bars.

    Raises:
        SystemExit: the command failed.
    """
    command = [sys.executable, "-m", "photonpano.cli", *args]
    print("$ photonpano", " ".join(args), flush=True)
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}  # lines in the order a terminal shows them
    result = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=work,
                            env=environment)
    lines = [line.rstrip() for line in result.stdout.splitlines() if "━" not in line and "\r" not in line]
    text = "\n".join(lines).strip("\n") + "\n"
    print(text, flush=True)
    if result.returncode:
        raise SystemExit(f"photonpano {args[0]} failed with exit code {result.returncode}:\n{text[-2000:]}")
    return text


def to_8bit(image: np.ndarray) -> np.ndarray:
    """A 16-bit (or 8-bit) tone-mapped PNG image as 8-bit."""
    return (image // 257).astype(np.uint8) if image.dtype == np.uint16 else image


def write_png(folder: Path, name: str, image: np.ndarray) -> None:
    """Write ``folder/<name>`` at maximum PNG compression, refusing files over 300 KB."""
    path = folder / name
    cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    size = path.stat().st_size
    print(f"wrote {path} ({image.shape[1]}x{image.shape[0]}, {size / 1000:.0f} KB)")
    if size > MAX_BYTES:
        raise SystemExit(f"{path} is {size} bytes, more than {MAX_BYTES}")


def merged_near(folder: Path, frame: int) -> tuple[np.ndarray, int]:
    """The dumped merged frame (tone-mapped PNG) whose reference frame is nearest ``frame``."""
    references = np.load(folder / "references.npy")
    i = int(np.argmin(np.abs(references - frame)))
    return cv2.imread(str(folder / f"merged_{i:04d}_frame{int(references[i])}.png"), cv2.IMREAD_UNCHANGED), \
        int(references[i])


def run(work: Path) -> dict[str, str]:
    """Run the tutorial's commands in ``work``; return each command's output."""
    return {name: photonpano(work, *args) for name, args in COMMANDS.items()}


def measure(work: Path) -> dict[str, float]:
    """The page's figures (:data:`FIGURES`) from the runs in ``work``."""
    summary = json.loads((work / "demo-out" / "run.json").read_text())
    truth, levels = summary["ground_truth"], summary["levels"]
    cube = np.load(work / "capture.npy", mmap_mode="r")
    middle = cube.shape[0] // 2
    references = np.load(work / "levels-out" / "level_1" / "references.npy")
    group = int(summary["group_size"]["group_size"])
    homography = np.load(work / "demo-out" / "homographies.npy")[middle]
    return {
        "binary_mean": float(np.unpackbits(np.asarray(cube[middle]), axis=-1).mean()),
        "group_size": group,
        "group_ms": 1e3 * group / float(summary["source"]["frame_rate_hz"]),
        "group_pan_px": group * float(summary["spec"]["source"]["speed_px_per_frame"]),
        "group_reference": int(references[np.argmin(np.abs(references - middle))]),
        "inliers_level_1": float(levels[0]["median_inliers"]),
        "rmse_level_1": float(levels[0]["trajectory_rmse_px"]),
        "rmse_final": float(truth["trajectory_rmse_px"]),
        "max_final": float(truth["trajectory_max_px"]),
        "h_tx": float(homography[0, 2] / homography[2, 2]),
        "h_ty": float(homography[1, 2] / homography[2, 2]),
        "psnr": float(truth["psnr_db"]),
        "psnr_true": float(truth["psnr_true_homographies_db"]),
        "psnr_gap": float(truth["psnr_gap_db"]),
        "canvas_width": int(summary["panorama"]["width"]),
        "canvas_height": int(summary["panorama"]["height"]),
    }


def pictures(work: Path, folder: Path) -> None:
    """Write the page's pictures from the runs in ``work`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    cube = np.load(work / "capture.npy", mmap_mode="r")
    middle = cube.shape[0] // 2
    write_png(folder, "binary_frame.png", np.unpackbits(np.asarray(cube[middle]), axis=-1) * np.uint8(255))
    levels = sorted((work / "levels-out").glob("level_*"), key=lambda p: int(p.name.split("_")[1]))
    reference = middle
    for level in (levels[0], levels[-1]):  # the same group (a level-1 one) at both levels
        image, reference = merged_near(level, reference)
        write_png(folder, "merged_level_1.png" if level == levels[0] else "merged_level_3.png", to_8bit(image))
    write_png(folder, "trajectory.png", cv2.imread(str(work / "demo-out" / "trajectory.png"), cv2.IMREAD_UNCHANGED))
    panorama = to_8bit(cv2.imread(str(work / "demo-out" / "panorama.png"), cv2.IMREAD_UNCHANGED))
    if panorama.shape[1] > PANORAMA_WIDTH:
        height = round(panorama.shape[0] * PANORAMA_WIDTH / panorama.shape[1])
        panorama = cv2.resize(panorama, (PANORAMA_WIDTH, height), interpolation=cv2.INTER_AREA)
    write_png(folder, "panorama.png", panorama)


def _format(name: str, value: float) -> str:
    """``value`` written as the page writes figure ``name``."""
    form = FIGURES[name][0]
    return form.format(int(round(value)) if form.endswith("d}") else value)


def render(page: str, figures: dict[str, float], outputs: dict[str, str]) -> str:
    """``page`` with every marked figure and command output replaced by the new ones.

    Raises:
        KeyError: the page marks a figure or an output this script does not make.
    """
    page = FIGURE.sub(lambda m: f"{_format(m.group(2), figures[m.group(2)])}<!--{m.group(2)}-->", page)
    return OUTPUT.sub(lambda m: m.group(1) + outputs[m.group(2)] + m.group(4), page)


def drifts(page: str, figures: dict[str, float], outputs: dict[str, str]) -> list[str]:
    """One line for every figure, output line or number of ``page`` that the new runs no longer support.

    Args:
        page: the tutorial's Markdown.
        figures: the new figures (:func:`measure`).
        outputs: the new command outputs (:func:`run`).

    Returns:
        The drifts, empty when the page is current (within the tolerances).
    """
    found = []
    marked = {name: float(value) for value, name in FIGURE.findall(page)}
    for name in sorted(set(FIGURES) - set(marked)):
        found.append(f"figure {name} ({FIGURES[name][2]}) is not on the page")
    for value, name in FIGURE.findall(page):
        tolerance, what = FIGURES[name][1], FIGURES[name][2]
        if abs(float(value) - figures[name]) > tolerance + 1e-9:
            found.append(f"figure {name} ({what}): the page says {value}, the run gives "
                         f"{_format(name, figures[name])} (tolerance {tolerance})")
    for _, name, text, _ in OUTPUT.findall(page):
        # lines are matched by their words (numbers masked): blank lines and the order in
        # which stdout and stderr lines interleave in a pipe are not compared
        old = [line for line in text.splitlines() if line.strip()]
        new: dict[str, list[str]] = {}
        for line in outputs[name].splitlines():
            if line.strip():
                new.setdefault(NUMBER.sub("#", line), []).append(line)
        for before in old:
            same = new.get(NUMBER.sub("#", before))
            if not same:
                found.append(f"output of {name}: the page says {before!r}, the run prints no such line")
            else:
                found += [f"output of {name}: {problem}" for problem in _line_drift(before, same.pop(0))]
        found += [f"output of {name}: the run prints {line!r}, the page does not"
                  for lines in new.values() for line in lines]
    return found


def _line_drift(before: str, now: str) -> list[str]:
    """The differences between two output lines beyond their tolerance (timings ignored).

    :data:`SIGMA_TOLERANCE` for the predicted per-frame error, else :data:`OUTPUT_TOLERANCE`.
    """
    old, new = NUMBER.split(before), NUMBER.split(now)
    if len(old) != len(new) or old[::2] != new[::2]:
        return [f"the page says {before!r}, now {now!r}"]
    problems = []
    relative, absolute = SIGMA_TOLERANCE if before.startswith("predicted per-frame error") else OUTPUT_TOLERANCE
    for i in range(1, len(old), 2):
        if old[i + 1].startswith(" s"):  # a timing
            continue
        a, b = float(old[i]), float(new[i])
        if abs(a - b) > max(relative * abs(a), absolute):
            problems.append(f"{old[i]} became {new[i]} in {before!r}")
    return problems


def picture_drifts(new: Path, old: Path) -> list[str]:
    """One line for every regenerated picture in ``new`` that differs from its copy in ``old``.

    Only the tutorial's own pictures are compared (``old`` is docs/img/, which other
    pages' pictures share).
    """
    found = []
    for fresh in sorted(new.glob("*.png")):
        path = old / fresh.name
        a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(fresh), cv2.IMREAD_UNCHANGED)
        if a is None or a.shape != b.shape:
            found.append(f"picture {path.name}: {None if a is None else a.shape} on the page, {b.shape} now")
            continue
        difference = float(np.abs(to_8bit(a).astype(float) - to_8bit(b).astype(float)).mean())
        if difference > PICTURE_TOLERANCE:
            found.append(f"picture {path.name}: mean difference {difference:.1f} grey levels "
                         f"(tolerance {PICTURE_TOLERANCE})")
    return found


def main() -> None:
    """Run the tutorial's commands; rewrite the page's figures, outputs and pictures, or check them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if the page drifted")
    parser.add_argument("--work", type=Path, help="scratch folder (default: a temporary one, deleted)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="photonpano-tutorial-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        outputs = run(work)
        figures = measure(work)
        print(json.dumps(figures, indent=1))
        page = PAGE.read_text(encoding="utf-8")
        if args.check:
            pictures(work, work / "img")
            found = drifts(page, figures, outputs) + picture_drifts(work / "img", IMG)
            if found:
                raise SystemExit("docs/tutorial.md drifted (python docs/tutorial_generate.py rewrites it):\n"
                                 + "\n".join(found))
            print("docs/tutorial.md is current")
            return
        pictures(work, IMG)
        PAGE.write_text(render(page, figures, outputs), encoding="utf-8")
        print(f"rewrote {PAGE}")
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
