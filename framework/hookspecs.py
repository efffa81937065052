"""Hook specifications of photonpano, grouped by phase in the order they fire.

Stage plugins implement a zero-argument ``photonpano_register_<stage plural>`` hook that
returns *config classes* (subclasses of the stage's config base in
:mod:`photonpano.stages`, each pinning a unique ``plugin`` key). The work itself is done
by the objects their ``build()`` returns. Observers implement the lifecycle hooks.

Hooks are called with keyword arguments; an implementation may accept fewer arguments
than the spec lists (pluggy's opt-in arguments), so arguments can be added later
without breaking plugins.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from . import hookspec

if TYPE_CHECKING:
    from .compose import Panorama
    from .records import LevelResult
    from .stages import (
        CompositorConfig,
        InterpolatorConfig,
        LocatorConfig,
        MergerConfig,
        PhotonSource,
        PoseEstimatorConfig,
        ResamplerConfig,
        SourceConfig,
    )


# --- registration: one hook per stage kind ---------------------------------------


@hookspec
def photonpano_register_sources() -> list[type[SourceConfig]]:
    """Offer source plugins (where binary frames come from).

    Returns:
        Config classes, each a :class:`~photonpano.stages.SourceConfig` subclass whose
        ``plugin`` field is a ``Literal`` key unique across installed plugins.

    .. versionadded:: 0.1
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec
def photonpano_register_resamplers() -> list[type[ResamplerConfig]]:
    """Offer resampler plugins (which frames form each virtual exposure).

    Returns:
        :class:`~photonpano.stages.ResamplerConfig` subclasses with unique keys.

    .. versionadded:: 0.1
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec
def photonpano_register_mergers() -> list[type[MergerConfig]]:
    """Offer merger plugins (virtual exposures from the frames of each group).

    Returns:
        :class:`~photonpano.stages.MergerConfig` subclasses with unique keys.

    .. versionadded:: 0.1
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Offer locator plugins (registration of pairs of merged frames).

    Returns:
        :class:`~photonpano.stages.LocatorConfig` subclasses with unique keys.

    .. versionadded:: 0.1
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec
def photonpano_register_interpolators() -> list[type[InterpolatorConfig]]:
    """Offer interpolator plugins (homographies for every binary frame).

    Returns:
        :class:`~photonpano.stages.InterpolatorConfig` subclasses with unique keys.

    .. versionadded:: 0.1
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec
def photonpano_register_compositors() -> list[type[CompositorConfig]]:
    """Offer compositor plugins (the panorama from every binary frame and its homography).

    Returns:
        :class:`~photonpano.stages.CompositorConfig` subclasses with unique keys.

    .. versionadded:: 0.2
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec
def photonpano_register_pose_estimators() -> list[type[PoseEstimatorConfig]]:
    """Offer pose estimator plugins (experimental: 6-DoF camera poses, ``photonpano pose``).

    Returns:
        :class:`~photonpano.stages.PoseEstimatorConfig` subclasses with unique keys.

    .. versionadded:: 0.1
    """
    raise NotImplementedError  # a specification: pluggy calls the implementations, never this


@hookspec(firstresult=True)
def photonpano_source_for_input(path: Path) -> dict[str, Any] | None:
    """Choose a source for ``photonpano pano INPUT``.

    Called in LIFO registration order until one implementation returns a result.

    Args:
        path: the INPUT argument (a file or a folder; it may not exist).

    Returns:
        The ``source`` section of a spec (a mapping with a ``plugin`` key) that reads
        ``path``, or None if this plugin does not handle it.

    .. versionadded:: 0.1
    """


# --- lifecycle: observers (progress bars, per-level dumps, logging) --------------


@hookspec
def photonpano_run_start(spec: Any, source: PhotonSource, out_dir: Path | None) -> None:
    """Called once the source is open, before the first level.

    Args:
        spec: the validated pipeline spec.
        source: the opened capture.
        out_dir: the output folder (locked by this run; the previous run's outputs
            removed with ``--force``), or None for a run kept in memory
            (``photonpano.run`` without ``out_dir``). Files an observer writes there are
            added to the run's manifest; write them through :func:`photonpano.outputs.atomic_path`.

    .. versionadded:: 0.1
    """


@hookspec
def photonpano_progress(task: str, total: int | None, advance: int) -> None:
    """Report progress of long work.

    Called with ``advance=0`` and the ``total`` work units when ``task`` starts, then
    with the units done since the previous call.

    Args:
        task: a short description such as ``"level 2: merge"``.
        total: the number of work units (groups, frames), or None when unknown.
        advance: units done since the previous call.

    .. versionadded:: 0.1
    """


@hookspec
def photonpano_level_finished(level: LevelResult, spec: Any, source: PhotonSource, out_dir: Path | None) -> None:
    """Called after each level with its groups, merged frames, pairs and homographies.

    Args:
        level: the level's result (``level.merged`` is set when the spec asks for
            merged-frame outputs).
        spec: the validated pipeline spec.
        source: the capture.
        out_dir: the output folder, or None for a run kept in memory.

    .. versionadded:: 0.1
    """


@hookspec
def photonpano_panorama_finished(panorama: Panorama, spec: Any, source: PhotonSource, out_dir: Path | None) -> None:
    """Called once the panorama is composited and written, with the capture still open.

    Observers that composite more from the same photons (a colour panorama, say) use
    ``panorama.homographies`` and the canvas shape from here rather than re-opening
    the source and reading ``homographies.npy``.

    Args:
        panorama: the run's :class:`~photonpano.compose.Panorama` (frame-to-canvas
            homographies of every binary frame, flux on the canvas).
        spec: the validated pipeline spec.
        source: the opened capture.
        out_dir: the output folder, or None for a run kept in memory.

    .. versionadded:: 0.2
    """


@hookspec
def photonpano_run_finished(spec: Any, summary: dict[str, Any], out_dir: Path | None) -> None:
    """Called after all other outputs are written, just before ``run.json`` (written last).

    Files written here are part of the run (its manifest); a hook that raises fails
    the run, which then removes its outputs.

    Args:
        spec: the validated pipeline spec.
        summary: the content of ``run.json``.
        out_dir: the output folder, or None for a run kept in memory.

    .. versionadded:: 0.1
    """
