"""The base of every plugin config: a validated, frozen, documented pydantic record.

Each stage kind's config base (:mod:`photonpano.stages`) derives from
:class:`StageConfig`; a plugin's config pins ``plugin`` to its key and builds the
working stage object.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator

from .errors import MissingDependency

__all__ = ["StageConfig"]


class StageConfig(BaseModel):
    """Base of every plugin config: a validated, immutable, documented record.

    Subclasses pin ``plugin`` to a ``Literal`` key (kebab-case, e.g. ``"opencv-sift"``),
    document each field with a docstring on the line below it (units in the text and,
    where ambiguous, in the name), and implement :meth:`build`.

    Class attributes:
        stage: the stage kind, set by the stage base classes.
        requires: import names of optional packages the plugin needs.
        install_hint: the command that installs them, e.g. ``pip install 'photonpano[kornia]'``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    plugin: str
    stage: ClassVar[str] = ""
    requires: ClassVar[tuple[str, ...]] = ()
    install_hint: ClassVar[str] = ""

    @field_validator("*", mode="after")
    @classmethod
    def _absolute_paths(cls, value: Any, info: ValidationInfo) -> Any:
        """Make relative paths absolute, against ``context["base_dir"]`` or the working directory.

        Specs are saved with absolute paths, so a saved ``spec.yaml`` runs from anywhere;
        :func:`photonpano.spec.load_spec` resolves a spec file's own relative paths
        against the file's folder before this runs.
        """
        base = Path((info.context or {}).get("base_dir") or Path.cwd())
        if isinstance(value, Path):
            return value if value.is_absolute() else base / value
        if isinstance(value, list) and value and all(isinstance(v, Path) for v in value):
            return [v if v.is_absolute() else base / v for v in value]
        return value

    @classmethod
    def missing_requirements(cls) -> list[str]:
        """Return the import names in ``requires`` that are not installed (no import)."""
        return [name for name in cls.requires if importlib.util.find_spec(name) is None]

    @classmethod
    def check_available(cls) -> None:
        """Raise :class:`MissingDependency` if an optional requirement is missing."""
        missing = cls.missing_requirements()
        if missing:
            key = cls.model_fields["plugin"].default
            raise MissingDependency(
                f"{cls.stage} {key!r} needs {', '.join(missing)}: {cls.install_hint or 'install it'}"
            )

    def build(self) -> Any:
        """Return the working stage object configured by this record."""
        raise NotImplementedError(f"{type(self).__name__}.build")
