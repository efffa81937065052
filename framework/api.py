"""The Python API: one call runs a pipeline, one call reads a finished run back.

Example:
    >>> import photonpano
    >>> result = photonpano.run({"source": {"plugin": "simulate", "frames": 3000}},
    ...                         progress=False)  # doctest: +SKIP
    >>> result.homographies.shape, result.panorama.ndim  # doctest: +SKIP
    ((3000, 3, 3), 2)

``run`` takes what ``photonpano run`` takes (a spec file, YAML text or a mapping, plus
``--set``-style overrides) and returns the homographies, the panorama and the
``run.json`` summary in memory; it writes files only when ``out_dir`` is given.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .errors import PhotonpanoError, SpecError
from .pipeline import RunResult

__all__ = ["run", "load", "RunResult"]


def _spec_data(spec: str | Path | Mapping[str, Any]) -> tuple[dict[str, Any], Any, str, Path | None]:
    """Return ``(mapping, yaml node or None, origin for messages, folder of the spec file)``."""
    if isinstance(spec, Mapping):
        return dict(spec), None, "spec", None
    if isinstance(spec, Path) or (isinstance(spec, str) and "\n" not in spec and (spec.strip().endswith(
            (".yaml", ".yml")) or Path(spec.strip()).exists())):  # an existing file: a capture is named so
        path = Path(spec)
        if not path.is_file():
            raise SpecError(f"spec file {path} does not exist")
        return {}, None, str(path), path  # read by load_spec (line numbers, relative paths)
    if isinstance(spec, str):
        from .yaml_guard import load_yaml

        data, node = load_yaml(spec, "spec text")  # the same guards as spec files (alias bombs, duplicates)
        if not isinstance(data, dict):
            raise SpecError(f"spec text: a spec must be a mapping of stage and setting names, got "
                            f"{type(data).__name__}")
        return data, node, "spec text", None
    raise SpecError(f"spec: expected a file path, YAML text or a mapping, got {type(spec).__name__}")


def _override_strings(overrides: Sequence[str] | Mapping[str, Any] | None) -> list[str]:
    """``{"locator.ratio": 0.7}`` or ``["locator.ratio=0.7"]`` -> ``["locator.ratio=0.7"]``."""
    if overrides is None:
        return []
    if isinstance(overrides, Mapping):
        return [f"{key}={json.dumps(value, default=str)}" for key, value in overrides.items()]
    if isinstance(overrides, str):
        return [overrides]
    return list(overrides)


def run(spec: str | Path | Mapping[str, Any], out_dir: str | Path | None = None,
        overrides: Sequence[str] | Mapping[str, Any] | None = None, *, progress: bool = True,
        force: bool = False, host: Any = None, resume: bool = False) -> RunResult:
    """Run a pipeline spec and return its results (the Python face of ``photonpano run``).

    Args:
        spec: a YAML spec file (a ``Path``, or a ``str`` ending in ``.yaml``/``.yml`` or
            naming an existing file), YAML text, or a mapping such as ``{"source": {"plugin": "simulate"}}``. Omitted
            stages and settings take their defaults (those of ``photonpano pano``).
            Relative paths in a spec file resolve against the file's folder, others
            against the working directory.
        out_dir: output folder to write the usual files into (``homographies.npy``,
            ``panorama.npy``, ``run.json``, ...; see ``docs/outputs.md``); None keeps
            everything in memory and writes nothing.
        overrides: ``["stage.field=value", ...]`` (values parsed as YAML, as ``--set``)
            or a mapping ``{"stage.field": value}``.
        progress: show progress bars (tqdm: widgets in a notebook, text in a terminal).
        force: allow writing into a non-empty ``out_dir``.
        resume: continue the interrupted run in ``out_dir`` from its last finished level
            (the same spec; the results equal those of an uninterrupted run).
        host: a :class:`~photonpano.host.PluginHost` to use (default: a new one that
            loads every installed plugin).

    Returns:
        A :class:`~photonpano.pipeline.RunResult`: ``homographies`` (T, 3, 3) float64
        frame-to-canvas homographies, ``panorama`` (Hc, Wc) float32 linear flux in
        photons/s (NaN where unobserved), ``summary`` (the ``run.json`` content) and
        ``spec`` (the validated spec with every default filled in).

    Raises:
        SpecError: the spec is missing, not YAML (a capture file is named as such, with
            ``photonpano pano``), or invalid (every problem listed).
        PhotonpanoError: any other expected failure (unreadable capture, a stage that
            cannot produce output, a non-empty ``out_dir`` without ``force``).
    """
    from .host import PluginHost
    from .pipeline import run_pipeline
    from .spec import apply_overrides, load_spec, validate_spec

    host = host or PluginHost()
    data, node, origin, path = _spec_data(spec)
    sets = _override_strings(overrides)
    if path is not None:
        parsed = load_spec(path, host, sets)
    else:
        parsed = validate_spec(apply_overrides(data, sets), host, origin=origin, node=node, overridden=sets)
    if getattr(parsed, "pose_estimator", None) is not None:
        raise SpecError(f"{origin}: a spec with a pose_estimator runs with photonpano.pose_run.run_pose "
                        "(or `photonpano run`), not photonpano.run")
    observer = None
    if progress:
        from .progress import TqdmProgress

        observer = TqdmProgress()
        host.register(observer, name="api-progress")
    try:
        return run_pipeline(parsed, Path(out_dir) if out_dir is not None else None, host, force=force,
                            resume=resume)
    finally:
        if observer is not None:
            observer.stop()
            host.unregister("api-progress")


def load(out_dir: str | Path, host: Any = None) -> RunResult:
    """Read a finished run back from its output folder.

    Args:
        out_dir: a folder written by ``photonpano run``/``pano``/``demo`` or :func:`run`.
        host: the plugin host used to validate the saved ``spec.yaml`` (default: a new
            one); if the spec's plugins are no longer installed, ``spec`` is the plain
            mapping from ``run.json`` instead.

    Returns:
        A :class:`~photonpano.pipeline.RunResult` with ``homographies`` (T, 3, 3)
        float64, ``panorama`` (Hc, Wc) float32 flux in photons/s, ``summary`` (the
        ``run.json`` content), ``spec`` and ``uncertainty`` ((T,) float64 per-frame
        sigma in pixels, None for a run without ``uncertainty.npy``).

    Raises:
        PhotonpanoError: if the folder holds no finished run (``run.json`` is written
            last, so its absence means the run did not finish) or a file is unreadable.
    """
    from .host import PluginHost
    from .spec import validate_spec

    folder = Path(out_dir)
    summary_path = folder / "run.json"
    if not summary_path.is_file():
        raise PhotonpanoError(f"{folder}: no run.json, so not a finished photonpano run")
    try:
        summary = json.loads(summary_path.read_text())
        homographies = np.load(folder / "homographies.npy", allow_pickle=False)
        panorama = np.load(folder / "panorama.npy", allow_pickle=False)
        sigma_path = folder / "uncertainty.npy"
        uncertainty = np.load(sigma_path, allow_pickle=False) if sigma_path.is_file() else None
    except (OSError, ValueError) as exc:
        raise PhotonpanoError(f"{folder}: cannot read the run: {exc}") from None
    try:
        spec: Any = validate_spec(summary["spec"], host or PluginHost(), origin=str(summary_path))
    except PhotonpanoError:
        spec = summary["spec"]
    return RunResult(spec=spec, homographies=homographies, panorama=panorama, summary=summary, out_dir=folder,
                     uncertainty=uncertainty)
