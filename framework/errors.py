"""Exceptions of photonpano. Each prints as one line that names the culprit."""

from __future__ import annotations

__all__ = ["PhotonpanoError", "SpecError", "PluginError", "MissingDependency", "SourceError", "StageError",
           "OutputError"]


class PhotonpanoError(Exception):
    """Base class: an error the command line prints as one line, without a traceback."""


class SpecError(PhotonpanoError):
    """A pipeline spec (YAML file or ``--set`` override) is invalid.

    The message lists every problem, each with its YAML line, stage, plugin and field.
    """


class PluginError(PhotonpanoError):
    """A plugin is broken: it failed to import, registered a bad object, or a key twice."""


class MissingDependency(PluginError):
    """A selected plugin needs an optional package that is not installed."""


class SourceError(PhotonpanoError):
    """A capture could not be read: missing file, wrong dtype, shape or layout."""


class StageError(PhotonpanoError):
    """A pipeline stage could not produce any output (e.g. every pair failed to register)."""

    def __init__(self, stage: str, plugin: str, reason: str) -> None:
        super().__init__(f"{stage} ({plugin}): {reason}")
        self.stage, self.plugin, self.reason = stage, plugin, reason


class OutputError(PhotonpanoError):
    """The output folder cannot be written (in use, not empty, read-only, full) or resumed."""
