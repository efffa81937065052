"""Build helpers of the API reference, loaded by ``mkdocs.yml`` (not a docs page).

- As an mkdocs hook, ``on_config`` links ``build/api-src/photonpano`` to ``framework/``
  so that griffe reads the sources statically (it expects the folder to carry the
  package's name; the installed package maps ``photonpano`` to ``framework/``). Static
  analysis keeps attribute docstrings, which inspection loses.
- As a griffe extension, :class:`ReSTRoles` turns the reST markup in docstrings into
  Markdown with the converter of the generated pages
  (:func:`photonpano.docgen.rst_inline_to_markdown`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import griffe
from photonpano.docgen import rst_inline_to_markdown

SOURCE_LINK = Path("build", "api-src", "photonpano")
"""Where the link to ``framework/`` goes, relative to the folder of ``mkdocs.yml``."""


def on_config(config: Any) -> None:
    """Create ``build/api-src/photonpano`` -> ``framework/`` (mkdocs hook)."""
    root = Path(config.config_file_path).parent
    link = root / SOURCE_LINK
    target = root / "framework"
    if link.is_symlink() and link.resolve() == target.resolve():
        return
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink():
        link.unlink()
    link.symlink_to(target.resolve(), target_is_directory=True)


class ReSTRoles(griffe.Extension):
    """Rewrite every docstring's reST roles and literals as Markdown code."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        """Convert ``obj``'s docstring in place once the object tree is built."""
        if obj.docstring is not None:
            obj.docstring.value = rst_inline_to_markdown(obj.docstring.value)

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        """Convert the package's own docstring (``on_object`` skips the root)."""
        self.on_object(obj=pkg)
