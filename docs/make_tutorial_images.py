"""Make the pictures of docs/tutorial.md from real runs of the tool.

Runs exactly the tutorial's commands in a scratch folder:

1. ``photonpano demo`` with ``source.cube_path`` set, so the simulated photon cube is
   also written as a bit-packed ``.npy`` file;
2. ``photonpano pano`` on that cube with every level's merged frames dumped (the
   paper's pairwise registration at every level, ``level_schemes: [pairwise]``);

then writes small 8-bit PNGs into ``docs/img/``: one binary frame of the cube, the
virtual exposure around the middle frame at level 1 and at the last level, the demo's
``trajectory.png`` and its panorama. Each PNG must stay under 300 KB.

Usage (from the repository root, a few minutes on two cores)::

    python docs/make_tutorial_images.py [--work SCRATCH_FOLDER]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

IMG = Path(__file__).parent / "img"
MAX_BYTES = 300_000
"""Largest PNG written (bytes), to keep the repository small."""
PANORAMA_WIDTH = 960
"""Wider panoramas are shrunk to this width (pixels) for the page."""


def photonpano(*args: str) -> str:
    """Run the ``photonpano`` CLI of this interpreter; return its output (echoed)."""
    command = [sys.executable, "-m", "photonpano.cli", *args]
    print("$ photonpano", " ".join(args), flush=True)
    result = subprocess.run(command, capture_output=True, text=True)
    print(result.stdout + result.stderr, flush=True)
    if result.returncode:
        raise SystemExit(f"photonpano {args[0]} failed with exit code {result.returncode}")
    return result.stdout


def to_8bit(image: np.ndarray) -> np.ndarray:
    """A 16-bit (or 8-bit) tone-mapped PNG image as 8-bit."""
    return (image // 257).astype(np.uint8) if image.dtype == np.uint16 else image


def write_png(name: str, image: np.ndarray) -> None:
    """Write ``docs/img/<name>`` at maximum PNG compression, refusing files over 300 KB."""
    path = IMG / name
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


def main() -> None:
    """Run the tutorial's commands and write its pictures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, help="scratch folder (default: a temporary one, deleted)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="photonpano-tutorial-"))
    work.mkdir(parents=True, exist_ok=True)
    IMG.mkdir(exist_ok=True)
    try:
        cube = work / "capture.npy"
        photonpano("demo", "-o", str(work / "demo-out"), "--set", f"source.cube_path={cube}")
        photonpano("pano", str(cube), "-o", str(work / "levels-out"),
                   "--set", "outputs.merged_frames=true", "--set", "level_schemes=[pairwise]")

        frames = np.load(cube, mmap_mode="r")
        middle = frames.shape[0] // 2
        binary = np.unpackbits(np.asarray(frames[middle]), axis=-1)
        write_png("binary_frame.png", binary * np.uint8(255))

        levels = sorted((work / "levels-out").glob("level_*"), key=lambda p: int(p.name.split("_")[1]))
        reference = middle
        for folder in (levels[0], levels[-1]):  # the same group (a level-1 one) at both levels
            image, reference = merged_near(folder, reference)
            print(f"{folder.name}: group around binary frame {reference}")
            write_png(f"merged_{folder.name}.png", to_8bit(image))

        shutil.copyfile(work / "demo-out" / "trajectory.png", IMG / "trajectory.png")
        write_png("trajectory.png", cv2.imread(str(IMG / "trajectory.png"), cv2.IMREAD_UNCHANGED))

        panorama = to_8bit(cv2.imread(str(work / "demo-out" / "panorama.png"), cv2.IMREAD_UNCHANGED))
        if panorama.shape[1] > PANORAMA_WIDTH:
            height = round(panorama.shape[0] * PANORAMA_WIDTH / panorama.shape[1])
            panorama = cv2.resize(panorama, (PANORAMA_WIDTH, height), interpolation=cv2.INTER_AREA)
        write_png("panorama.png", panorama)

        summary = json.loads((work / "demo-out" / "run.json").read_text())
        print(json.dumps({"ground_truth": summary.get("ground_truth"), "panorama": summary.get("panorama"),
                          "timings_s": summary.get("timings_s")}, indent=1))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
