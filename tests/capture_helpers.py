"""Writers of synthetic captures in real file formats, with ground truth, for the tests.

- :func:`simulate_raw_half`: a SwissSPAD2 colour half-array capture at the raw sensor
  layout (256x512, before the colour-SPAD fix), from the ``simulate`` source.
- :func:`simulate_highspeed_video`: a conventional high-speed camera (intensity frames
  with motion blur and read noise) panning across the bundled photograph.
- :func:`write_video`: frames to a video file with PyAV.
- :func:`reconstruct_simulated`: a ``simulate`` capture reconstructed by the pipeline,
  with its trajectory error and confidence report.
- :func:`load_suite`: the evaluation suite, ``benchmarks/suite.py``, as a module;
  :func:`load_benchmark` any other script of ``benchmarks/``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def embed_colorspad(packed: np.ndarray, seed: int = 1, block: int = 256) -> np.ndarray:
    """Put corrected (T, 254, 62) packed frames into raw (T, 256, 64) colour half-array frames.

    The inverse of the colour-SPAD fix: corrected pixel (y, x) sits at raw (y + 2, x),
    with columns 252:256 and 260:264 swapped; the rows and columns the fix crops hold
    random bits (p = 0.3), so a reader that misplaces them is caught. Works ``block``
    frames at a time (unpacked and drawn whole, 4300 frames took 6.7 GB).
    """
    rng = np.random.default_rng(seed)
    out = np.empty((len(packed), 256, 64), np.uint8)
    for start in range(0, len(packed), block):
        frames = np.unpackbits(packed[start:start + block], axis=-1)
        raw = (rng.random((len(frames), 256, 512), dtype=np.float32) < 0.3).astype(np.uint8)
        raw[:, 2:, :496] = frames
        raw[:, 2:, 252:256], raw[:, 2:, 260:264] = frames[:, :, 260:264], frames[:, :, 252:256]
        out[start:start + block] = np.packbits(raw, axis=-1)
    return out


def simulate_raw_half(frames: int, **simulate):
    """Simulate a colour half-array capture and return ``(capture, raw_packed)``.

    Args:
        frames: binary frames.
        **simulate: more ``SimulateConfig`` fields.

    Returns:
        The simulated 254x496 capture (with ``ground_truth``) and its raw (T, 256, 64)
        packed frames, MSB first.
    """
    from photonpano.plugins.sources.simulate import SimulateConfig

    cap = SimulateConfig(frames=frames, height=254, width=496, **simulate).build()
    return cap, embed_colorspad(np.asarray(cap.cube))


def write_video(path: Path, frames: np.ndarray, fps: float = 30, codec: str = "libx264", **options) -> None:
    """Write (T, H, W) uint8 grey frames to a video file with PyAV.

    Args:
        path: output file (``.mp4``, ``.avi``, ...).
        frames: grey frames.
        fps: container frame rate (INFINICAM exports say 30).
        codec: ``libx264`` (MP4), ``mjpeg`` (AVI), ``mpeg4``...
        **options: codec options, e.g. ``crf="18"``.
    """
    from fractions import Fraction

    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
        stream.options = {k: str(v) for k, v in options.items()}
        for frame in frames:
            image = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="gray")
            for packet in stream.encode(image):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def simulate_highspeed_video(frames: int = 1200, fps: float = 1000.0, height: int = 254, width: int = 496,
                             read_noise: float = 0.01, subframes: int = 4, seed: int = 0, **path):
    """Render a conventional high-speed camera panning across the bundled photograph.

    Each frame averages ``subframes`` renders across its exposure (motion blur), adds
    Gaussian read noise of ``read_noise`` (fraction of full scale) and is sRGB-encoded
    to 8 bits.

    Args:
        frames: number of frames.
        fps: frame rate.
        height: frame height.
        width: frame width.
        read_noise: standard deviation of the read noise, relative to full scale.
        subframes: renders averaged per frame.
        seed: noise seed.
        **path: ``SimulateConfig`` camera-path fields (speed_px_per_frame, vibration_px...).

    Returns:
        ``(codes, ground_truth)``: (T, H, W) uint8 sRGB frames and (T, 3, 3) float64
        frame-to-scene homographies (averaged over each exposure).
    """
    import cv2
    from photonpano.photons import linear_to_srgb
    from photonpano.plugins.sources.simulate import SimulateConfig, bundled_photo, camera_path, load_scene

    scene = load_scene(bundled_photo(), 1440)
    cfg = SimulateConfig(frames=frames * subframes, frame_rate_hz=fps * subframes, height=height, width=width,
                         **path)
    fine = camera_path(cfg, scene.shape)
    rng = np.random.default_rng(seed)
    codes = np.empty((frames, height, width), np.uint8)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for t in range(frames):
        acc = np.zeros((height, width), np.float32)
        for k in range(subframes):
            acc += cv2.warpPerspective(scene, fine[t * subframes + k], (width, height), flags=flags)
        linear = acc / subframes + rng.normal(0, read_noise, acc.shape).astype(np.float32)
        codes[t] = np.rint(linear_to_srgb(linear) * 255).astype(np.uint8)
    truth = fine.reshape(frames, subframes, 3, 3).mean(axis=1)  # exposure-average pose
    truth /= truth[:, 2:3, 2:3]
    return codes, truth


def reconstruct_simulated(source: dict, overrides=(), keep: list | None = None, levels: list | None = None):
    """Simulate a capture and reconstruct it as ``photonpano run`` would.

    Args:
        source: ``simulate`` settings (``plugin`` is added).
        overrides: ``--set``-style ``key=value`` strings for the spec.
        keep: a list the run's :class:`~photonpano.records.Panorama` is appended to.
        levels: a list the run's level rows (``run.json``'s ``levels``) are appended to.

    Returns:
        ``(error, report)``: the :class:`~photonpano.metrics.TrajectoryError` against the
        simulated truth and the confidence report (``run.json``'s, plus
        ``frame_uncertainty``).
    """
    from photonpano.host import PluginHost
    from photonpano.metrics import source_trajectory_error
    from photonpano.pipeline import reconstruct
    from photonpano.spec import apply_overrides, validate_spec

    spec = validate_spec(apply_overrides({"source": {"plugin": "simulate", **source}}, list(overrides)),
                         PluginHost(), origin="test")
    capture = spec.source.build()
    report: dict = {}
    homographies, stats, pano, _ = reconstruct(spec, capture, report=report)
    if keep is not None:
        keep.append(pano)
    if levels is not None:
        levels.extend(stats)
    return source_trajectory_error(homographies, capture), report


def load_benchmark(name: str, module_name: str | None = None):
    """Import ``benchmarks/<name>.py`` as a module (``<name>_benchmark`` unless ``module_name`` is given).

    The module is registered in ``sys.modules`` first: dataclasses look their module up.
    """
    import importlib.util
    import sys

    module_name = module_name or f"{name}_benchmark"
    spec = importlib.util.spec_from_file_location(module_name, Path(__file__).resolve().parents[1] / "benchmarks"
                                                  / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    return module


def load_suite():
    """Import ``benchmarks/suite.py`` (the evaluation suite) as the module ``suite``."""
    return load_benchmark("suite", "suite")
