"""Make the pictures of docs/real_scenes.md from real runs of the tool.

0. Flickering light: a simulated capture of the brick facade (20 000 frames, flux 0.5, a pan
   with a 5 px 30 Hz vibration) whose right half a 120 Hz lamp lights at 90 % depth: 100
   binary frames summed while the lamp is bright and while it is dark, and the per-frame
   trajectory error of a run with groups of 400 frames (not a whole number of the lamp's
   periods) against the default (groups of whole periods).
1. A simulated capture of the bundled office photo (20 000 frames, flux 0.5, a pan with a
   5 px 30 Hz vibration) crossed by a bright disc of radius 30 px at 0.08 px/frame,
   reconstructed with ``mosaic.reject_movers: 5``; its panorama composited by ``drizzle``
   with the plain merge and with the robust merge, and the robust merge's ``moving.png``.
2. The real Photron ball clip (``tests/data/highspeed/ball_12bit.mraw``) through
   ``photonpano pano`` with ``compositor.robust`` false and true.

Writes ``docs/img/flicker_facade.png``, ``docs/img/mover_office.png`` and
``docs/img/mover_ball.png`` (8-bit, each under 300 KB): for the movers, the plain panorama,
the robust one and the mask side by side or stacked.

Usage (from the repository root, about two minutes on two cores)::

    python docs/make_real_scene_images.py
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
IMG = ROOT / "docs" / "img"


def _grey(flux: np.ndarray, white: float) -> np.ndarray:
    """8-bit sRGB-ish grey of linear flux (``white`` to 255; NaN black)."""
    x = np.clip(np.nan_to_num(flux / white, nan=0.0), 0, 1) ** (1 / 2.2)
    return (255 * x).astype(np.uint8)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """The image with ``text`` in a black band above it."""
    band = np.zeros((22, image.shape[1]), np.uint8)
    cv2.putText(band, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 255, 1, cv2.LINE_AA)
    return np.vstack([band, image])


def flicker() -> np.ndarray:
    """Two sums of binary frames (lamp bright, lamp dark) and the error of two runs under the lamp."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from photonpano.host import PluginHost
    from photonpano.metrics import source_trajectory_error
    from photonpano.pipeline import reconstruct
    from photonpano.spec import apply_overrides, validate_spec

    source = {"plugin": "simulate", "photo": str(ROOT / "benchmarks" / "photos" / "facade_brick.jpg"),
              "frames": 20_000, "flux": 0.5, "vibration_px": 5.0, "vibration_hz": 30.0, "flicker_hz": 120.0,
              "flicker_depth": 0.9, "flicker_region": "right"}
    runs = {}
    for label, overrides in (("groups of 400 frames", ["group_size=400"]), ("default: whole periods", [])):
        spec = validate_spec(apply_overrides({"source": source}, overrides), PluginHost(), origin="docs")
        capture = spec.source.build()
        report: dict = {}
        homographies, _, _, _ = reconstruct(spec, capture, report=report)
        error = source_trajectory_error(homographies, capture)
        runs[f"{label}: {error.rmse_px:.2f} px, {report['status']}"] = error.per_frame_px
    middle = capture.n_frames // 2  # the frame there sees both halves of the facade
    lamp = capture.lamp[middle:middle + 834]
    figure, axes = plt.subplot_mosaic([["bright", "dark"], ["error", "error"]], figsize=(9, 6.2),
                                      height_ratios=[1, 1.1], layout="constrained")
    for key, start in (("bright", middle + int(np.argmax(lamp))), ("dark", middle + int(np.argmin(lamp)))):
        start -= 50
        counts = capture.sum_ranges(np.array([start, start + 100]))[0]
        axes[key].imshow(counts, cmap="gray", vmin=0, vmax=float(np.percentile(counts, 99.5)))
        axes[key].set_title(f"100 binary frames from frame {start}: lamp {key}", fontsize=10)
        axes[key].axis("off")
    for label, per_frame in runs.items():
        axes["error"].plot(per_frame, lw=0.8, label=label)
    axes["error"].set(xlabel="binary frame", ylabel="trajectory error (px)", ylim=(0, None))
    axes["error"].legend(fontsize=9)
    figure.canvas.draw()
    image = np.asarray(figure.canvas.buffer_rgba())[..., :3]
    plt.close(figure)
    return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)


def office() -> np.ndarray:
    """Plain merge, robust merge and mask of the simulated office capture crossed by a disc."""
    from photonpano.host import PluginHost
    from photonpano.pipeline import reconstruct
    from photonpano.spec import apply_overrides, validate_spec

    source = {"plugin": "simulate", "frames": 20_000, "flux": 0.5, "vibration_px": 5.0, "vibration_hz": 30.0,
              "mover_radius_px": 30.0, "mover_speed_px_per_frame": 0.08, "mover_intensity": 1.0}
    panels = []
    for robust in (False, True):
        spec = validate_spec(apply_overrides({"source": source}, ["mosaic.reject_movers=5",
                                                                  f"compositor.robust={str(robust).lower()}"]),
                             PluginHost(), origin="docs")
        _, _, pano, _ = reconstruct(spec, spec.source.build())
        white = float(np.nanpercentile(pano.flux, 99.5))
        panels.append(_label(_grey(pano.flux, white), "plain merge" if not robust else "robust merge"))
        if robust:
            panels.append(_label(np.where(pano.moving, 255, 0).astype(np.uint8), "moving.png"))
    return np.vstack(panels)


def ball() -> np.ndarray:
    """Plain merge, robust merge and mask of the Photron ball clip (static camera)."""
    clip = ROOT / "tests" / "data" / "highspeed" / "ball_12bit.mraw"
    panels = []
    with tempfile.TemporaryDirectory() as work:
        for robust in ("false", "true"):
            out = Path(work) / robust
            subprocess.run([str(Path(sys.executable).parent / "photonpano"), "-q", "pano", str(clip), "-o", str(out),
                            "--set", f"compositor.robust={robust}"], check=True)
            flux = np.load(out / "panorama.npy")
            panels.append(_label(_grey(flux, float(np.nanmax(flux))), "plain" if robust == "false" else "robust"))
            if robust == "true":
                panels.append(_label(cv2.imread(str(out / "moving.png"), cv2.IMREAD_GRAYSCALE), "moving.png"))
    return np.hstack([cv2.resize(p, (p.shape[1] // 2, p.shape[0] // 2), interpolation=cv2.INTER_AREA)
                      for p in panels])


def main() -> None:
    """Write the pictures (``--only NAME`` for one of flicker, office, ball)."""
    IMG.mkdir(parents=True, exist_ok=True)
    pictures = {"flicker": ("flicker_facade.png", flicker), "office": ("mover_office.png", office),
                "ball": ("mover_ball.png", ball)}
    chosen = sys.argv[sys.argv.index("--only") + 1:] if "--only" in sys.argv else list(pictures)
    for name, make in (pictures[key] for key in chosen):
        image = make()
        path = IMG / name
        cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        assert path.stat().st_size < 300_000, f"{path} is {path.stat().st_size} bytes"
        print(path, image.shape, path.stat().st_size)


if __name__ == "__main__":
    main()
