"""Performance benchmark (issues 5, 16, 27): a long SPAD capture reconstructed, against the floor.

Simulates (once, cached under ``benchmarks/cache/``) a 254x496 capture at 100 kHz, flux
0.5, of one of three scenes (``--scene``: ``office``, the bundled photo; ``city``, the
texture-rich ``benchmarks/photos/city_madison.jpg``; ``dark``,
``benchmarks/photos/interior_room.jpg`` dimmed to a mean linear intensity of 0.016, as the
evaluation suite's dark captures), on one of the camera paths users record (``--path``):

- ``pan``: 0.004 px/frame plus a 5 px, 30 Hz vibration;
- ``zigzag``: the same pan sweeping 40 px up and down every 20 000 frames (a path that
  doubles back over the scene), plus the vibration;
- ``shake``: the same pan plus a smooth random hand shake (8 px RMS, 0.5-10 Hz) and the
  vibration;

then, in a fresh process, runs the default pipeline (3 levels + final panorama) on the
cached bit-packed cube through the memory-mapped ``npy-cube`` source, and prints:

- wall and CPU time per stage and level, and in total;
- peak resident memory of the pipeline (the process's ``VmHWM``, reset after the floor
  pass and read before the ground truth is loaded);
- the floor: one pass over the memory-mapped cube from the page cache that unpacks and
  sums every bit, in blocks of 2 000 frames (``np.unpackbits(block, axis=-1).sum(0,
  dtype=np.uint32)``, measured in the same process), and the ratio pipeline / floor;
- the trajectory RMSE against ground truth;
- with ``--timeline``, the run's CPU use every 0.25 s and the stage the main thread was in
  (:class:`Timeline`): where the pipeline runs on one core of two;
- with ``--repeat N``, each capture N times, then their medians (a 2-core virtual machine's
  speed drifts within the hour; the floor, measured in each run, shows by how much).

Usage::

    python benchmarks/performance.py                  # 100 000 frames, pan
    python benchmarks/performance.py --path zigzag --frames 25000
    python benchmarks/performance.py --path pan,zigzag,shake   # one row per path
    python benchmarks/performance.py --scene office,city,dark --path pan,zigzag,shake  # 9 rows
    python benchmarks/performance.py --scene highcontrast_hubble   # any suite photo, by its stem
    python benchmarks/performance.py --scene /tmp/outside/rocket.png   # or any photo, by its path
    python benchmarks/performance.py --scaling        # 12.5k, 25k, 50k, 100k, 200k frames
    python benchmarks/performance.py --set locator.max_features=2000   # spec overrides
    python benchmarks/performance.py --path zigzag --scene texture_gravel --timeline  # where the time goes
    python benchmarks/performance.py --path zigzag --scene city --repeat 3   # and the medians of 3 runs
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

CACHE = Path(__file__).parent / "cache"
SIMULATION = {"plugin": "simulate", "speed_px_per_frame": 0.004, "vibration_px": 5.0, "vibration_hz": 30.0,
              "flux": 0.5, "seed": 1}
PATHS = {"pan": {}, "zigzag": {"path": "zigzag", "sweep_px": 40.0, "sweep_period_frames": 20_000},
         "shake": {"path": "shake", "shake_px": 8.0}}
"""Camera path -> simulate settings added to :data:`SIMULATION`."""
PHOTOS = Path(__file__).parent / "photos"
SCENES = {"office": {}, "city": {"photo": str(PHOTOS / "city_madison.jpg")},
          "dark": {"photo": str(PHOTOS / "interior_room.jpg"), "mean_intensity": 0.016}}
"""Scene -> simulate settings added to :data:`SIMULATION` (``office``: the bundled photo)."""


def scene_settings(scene: str) -> dict:
    """Simulate settings of ``scene``: one of :data:`SCENES`, the stem of an evaluation-suite photo, or a photo's path.

    Raises:
        SystemExit: for a name that is none of these (naming the choices).
    """
    if scene in SCENES:
        return SCENES[scene]
    photo = PHOTOS / f"{scene}.jpg"
    if not photo.exists():
        if Path(scene).is_file():
            return {"photo": str(Path(scene).resolve())}
        choices = sorted(SCENES) + sorted(p.stem for p in PHOTOS.glob("*.jpg"))
        raise SystemExit(f"--scene {scene!r}: expected one of {', '.join(choices)}, or a photo's path")
    return {"photo": str(photo)}


def scene_key(scene: str) -> str:
    """The cache's name for ``scene``: itself, or for a photo's path its stem and a hash of its bytes."""
    photo = Path(scene_settings(scene).get("photo", ""))
    if scene in SCENES or photo.parent == PHOTOS:
        return scene
    return f"{photo.stem}-{hashlib.sha256(photo.read_bytes()).hexdigest()[:12]}"


def simulation(path: str, frames: int, scene: str = "office") -> dict:
    """The simulate settings of the capture of ``frames`` frames of ``scene`` on camera path ``path``."""
    return {**SIMULATION, **scene_settings(scene), **PATHS[path], "frames": frames}


def cube_path(frames: int, camera: str = "pan", scene: str = "office") -> Path:
    """Return the cached cube for ``frames`` frames of ``scene`` on path ``camera``, simulating it first if needed."""
    from photonpano.plugins.sources.simulate import SimulateConfig

    path = CACHE / (f"{camera}_{frames}.npy" if scene == "office" else f"{scene_key(scene)}_{camera}_{frames}.npy")
    if not path.exists():
        CACHE.mkdir(exist_ok=True)
        partial = path.with_suffix(".partial.npy")
        partial.unlink(missing_ok=True)
        t0 = time.perf_counter()
        SimulateConfig(**simulation(camera, frames, scene), cube_path=partial).build()
        partial.rename(path)
        print(f"simulated {frames} frames in {time.perf_counter() - t0:.0f} s -> {path}", file=sys.stderr)
    return path


def floor_pass(path: Path, chunk: int = 2000) -> float:
    """Seconds for one numpy pass that unpacks and sums every bit of the cube, in blocks of ``chunk`` frames.

    The peak resident memory is reset after it, so what is reported is the pipeline's.
    """
    import numpy as np

    cube = np.load(path, mmap_mode="r")
    t0 = time.perf_counter()
    total = np.zeros((cube.shape[1], cube.shape[2] * 8), np.uint32)
    for start in range(0, len(cube), chunk):
        total += np.unpackbits(np.asarray(cube[start:start + chunk]), axis=-1).sum(axis=0, dtype=np.uint32)
    return time.perf_counter() - t0


def _reset_peak_memory() -> None:
    """Reset the kernel's peak resident memory of this process (Linux ``clear_refs``)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _peak_memory_mb() -> float:
    """Peak resident memory since the last reset, in MB (``VmHWM``; ``ru_maxrss`` elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class Timeline:
    """This process's CPU use and the main thread's stage, sampled every ``step_s`` seconds (a context manager).

    The stage is the main thread's outermost photonpano calls below ``reconstruct`` (the
    executor's own frames left out): while it waits for the workers, the call that
    handed them the work. Stretches where the process uses one core of two are the
    pipeline's serial parts.
    """

    def __init__(self, step_s: float = 0.05) -> None:
        import threading

        self.step_s, self.samples = step_s, []  # (seconds since start, cores used since the last sample, stage)
        self._main, self._stop = threading.main_thread().ident, threading.Event()
        self._thread = threading.Thread(target=self._sample, name="timeline", daemon=True)

    def __enter__(self) -> Timeline:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def _stage(self) -> str:
        names, frame = [], sys._current_frames().get(self._main)
        while frame is not None:
            module = frame.f_globals.get("__name__", "")
            if module.startswith("photonpano") and module != "photonpano.executor":
                names.append(frame.f_code.co_qualname)
            frame = frame.f_back
        names.reverse()
        start = names.index("reconstruct") + 1 if "reconstruct" in names else 0
        return " > ".join(names[start:start + 4])

    def _sample(self) -> None:
        import os

        t0 = last_t = time.perf_counter()
        last_cpu = sum(os.times()[:2])
        while not self._stop.wait(self.step_s):
            now, cpu = time.perf_counter(), sum(os.times()[:2])
            self.samples.append((now - t0, (cpu - last_cpu) / (now - last_t), self._stage()))
            last_t, last_cpu = now, cpu

    def table(self, bucket_s: float = 0.25) -> list[str]:
        """One line per ``bucket_s`` seconds: its start, the mean cores used and its most sampled stage."""
        from collections import Counter

        import numpy as np

        lines = []
        for start in np.arange(0.0, self.samples[-1][0] if self.samples else 0.0, bucket_s):
            inside = [s for s in self.samples if start <= s[0] < start + bucket_s]
            if inside:
                stage = Counter(s[2] for s in inside).most_common(1)[0][0]
                lines.append(f"{start:6.2f} s {np.mean([s[1] for s in inside]):4.2f} cores  {stage}")
        return lines


def run_once(frames: int, overrides: list[str] = (), camera: str = "pan", scene: str = "office",
             timeline: bool = False) -> dict:
    """Reconstruct the cached capture in this process and return the measurements (and a :class:`Timeline`'s table)."""
    from photonpano.host import PluginHost
    from photonpano.metrics import trajectory_error
    from photonpano.pipeline import reconstruct
    from photonpano.plugins.sources.simulate import SimulateConfig, bundled_photo, camera_path, load_scene
    from photonpano.spec import apply_overrides, validate_spec

    path = cube_path(frames, camera, scene)
    floor_s = floor_pass(path)
    data = apply_overrides({"source": {"plugin": "npy-cube", "path": str(path)}}, list(overrides))
    spec = validate_spec(data, PluginHost(), origin="benchmark")
    _reset_peak_memory()  # the floor pass's buffers are not the pipeline's
    sampler = Timeline() if timeline else None
    wall0, cpu0 = time.perf_counter(), time.process_time()
    with sampler or contextlib.nullcontext():
        source = spec.source.build()
        homographies, stats, pano, timings = reconstruct(spec, source)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    peak_mb = _peak_memory_mb()  # before the ground truth (a full-resolution scene) is loaded
    config = SimulateConfig(**simulation(camera, frames, scene))
    truth = camera_path(config, load_scene(config.photo or bundled_photo(), config.scene_width).shape)
    rmse = trajectory_error(homographies, truth, source.width, source.height).rmse_px
    return {"scene": scene, "path": camera, "frames": frames, "wall_s": wall, "cpu_s": cpu, "floor_s": floor_s,
            "ratio": wall / floor_s, "peak_rss_mb": peak_mb,
            "rmse_px": rmse, "timings_s": timings,
            "levels": [{"level": s["level"], "groups": s["groups"], **s["timings_s"]} for s in stats],
            "timeline": sampler.table() if sampler else None}


def measure(frames: int, overrides: list[str] = (), camera: str = "pan", scene: str = "office",
            timeline: bool = False) -> dict:
    """Run :func:`run_once` in a fresh process (so peak memory is the pipeline's own)."""
    cube_path(frames, camera, scene)  # simulate outside the measured process
    args = [a for o in overrides for a in ("--set", o)] + ["--timeline"] * timeline
    out = subprocess.run([sys.executable, __file__, "--worker", str(frames), "--path", camera, "--scene", scene, *args],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def report(r: dict) -> None:
    """Print one run's figures."""
    print(f"{r['scene']}, {r['path']}, {r['frames']} frames: wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s, "
          f"peak RSS {r['peak_rss_mb']:.0f} MB, "
          f"floor {r['floor_s']:.2f} s, pipeline/floor {r['ratio']:.1f}x, trajectory RMSE {r['rmse_px']:.3f} px")
    for level in r["levels"]:
        print(f"  level {level['level']}: {level['groups']} groups, merge {level['merge']:.1f} s, "
              f"locate {level['locate']:.1f} s, interpolate {level['interpolate']:.2f} s")
    print(f"  panorama {r['timings_s']['panorama']:.1f} s")
    if r.get("timeline"):
        print("  timeline (seconds from the source's opening, mean cores used, the main thread's stage):")
        print("\n".join(f"    {line}" for line in r["timeline"]))


def report_medians(runs: list[dict]) -> None:
    """Print the median wall, CPU and floor seconds and pipeline/floor ratio of repeated runs of one capture."""
    from statistics import median

    r = runs[0]
    walls = ", ".join(f"{x['wall_s']:.1f}" for x in runs)
    rmse = ", ".join(sorted({f"{x['rmse_px']:.3f}" for x in runs}))  # one value: the runs are deterministic
    print(f"{r['scene']}, {r['path']}, {r['frames']} frames, median of {len(runs)} runs: "
          f"wall {median(x['wall_s'] for x in runs):.1f} s ({walls}), CPU {median(x['cpu_s'] for x in runs):.1f} s, "
          f"floor {median(x['floor_s'] for x in runs):.2f} s, pipeline/floor {median(x['ratio'] for x in runs):.1f}x, "
          f"peak RSS at most {max(x['peak_rss_mb'] for x in runs):.0f} MB, trajectory RMSE {rmse} px")


def main() -> None:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--path", default="pan", help="camera path(s), comma-separated: pan, zigzag, shake")
    parser.add_argument("--scene", default="office",
                        help="scene(s), comma-separated: office, city, dark, a suite photo's stem or a photo's path")
    parser.add_argument("--scaling", action="store_true", help="print the 12.5k..200k scaling table")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="spec override, as in `photonpano run --set` (repeatable)")
    parser.add_argument("--timeline", action="store_true",
                        help="also print the run's CPU use every 0.25 s with the stage it was in")
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="run each capture N times and print their medians too (this machine's speed, and "
                             "the floor with it, drifts by 10-25 %% within an hour)")
    parser.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    cameras = [c.strip() for c in args.path.split(",") if c.strip()]
    scenes = [c.strip() for c in args.scene.split(",") if c.strip()]
    if unknown := set(cameras) - set(PATHS):
        parser.error(f"--path: unknown {sorted(unknown)}; expected {', '.join(PATHS)}")
    for scene in scenes:
        scene_settings(scene)  # an unknown name exits here, naming the choices
    if args.worker:
        print(json.dumps(run_once(args.worker, args.set, cameras[0], scenes[0], args.timeline)))
        return
    if args.repeat < 1:
        parser.error(f"--repeat {args.repeat}: expected a whole number of runs >= 1")
    if not args.scaling:
        for scene in scenes:
            for camera in cameras:
                runs = [measure(args.frames, args.set, camera, scene, args.timeline) for _ in range(args.repeat)]
                for r in runs:
                    report(r)
                if len(runs) > 1:
                    report_medians(runs)
        return
    print(f"{'path':>7} {'frames':>8} {'wall s':>7} {'CPU s':>7} {'floor s':>7} {'ratio':>6} {'RSS MB':>7} "
          f"{'RMSE px':>8}")
    for camera in cameras:
        for frames in (12_500, 25_000, 50_000, 100_000, 200_000):
            r = measure(frames, args.set, camera)
            print(f"{camera:>7} {frames:>8} {r['wall_s']:>7.1f} {r['cpu_s']:>7.1f} {r['floor_s']:>7.2f} "
                  f"{r['ratio']:>6.1f} {r['peak_rss_mb']:>7.0f} {r['rmse_px']:>8.3f}", flush=True)


if __name__ == "__main__":
    main()
