"""Compiled kernels with numba, cached on disk outside the installed package.

``numba.njit(cache=True)`` writes its cache next to the source file (``__pycache__``)
whenever that folder is writable. For an installed package that is
``site-packages/photonpano/``, and the files it leaves there outlive an uninstall:
a later ``pip install -e .`` then finds a stale ``photonpano`` folder that shadows the
editable install (``ImportError: cannot import name 'hookspec'``). :func:`cached_njit`
compiles with numba's cache in a per-user folder instead (numba's own
``NUMBA_CACHE_DIR`` mechanism, applied to photonpano's kernels only), so the first run
compiles once (a few seconds) and later runs load the compiled code.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

__all__ = ["cache_dir", "cached_njit"]


def cache_dir() -> Path:
    """Return the folder of photonpano's compiled-kernel cache.

    ``$PHOTONPANO_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/photonpano`` (default
    ``~/.cache/photonpano``), with a ``numba`` sub-folder for the kernels. A user who
    sets numba's own ``NUMBA_CACHE_DIR`` keeps it (see :func:`cached_njit`).
    """
    root = os.environ.get("PHOTONPANO_CACHE_DIR")
    if not root:
        root = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "photonpano")
    return Path(root) / "numba"


def cached_njit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """Decorate a function like ``numba.njit(cache=True, **options)``, caching per user.

    numba picks a function's cache folder when the function is decorated, from
    ``numba.config.CACHE_DIR`` (``NUMBA_CACHE_DIR``) if set, else the source's
    ``__pycache__``. This decorator sets that folder to :func:`cache_dir` while it
    decorates, then restores it, so other numba users in the process are unaffected.
    If the user set ``NUMBA_CACHE_DIR``, that folder is used. If the cache folder
    cannot be created, the kernel is compiled at first call without a disk cache.

    Args:
        **options: numba ``njit`` options (e.g. ``nogil=True``, ``parallel=True``).

    Returns:
        A decorator producing a numba dispatcher.
    """
    import numba
    from numba import njit

    # numba sets its settings on numba.config from NUMBA_* variables at import: attributes mypy cannot see
    config: Any = numba.config

    def decorate(function: Callable[..., Any]) -> Any:
        if config.CACHE_DIR:
            return njit(cache=True, **options)(function)
        folder = cache_dir()
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            return njit(cache=False, **options)(function)
        previous = config.CACHE_DIR
        config.CACHE_DIR = str(folder)
        try:
            return njit(cache=True, **options)(function)
        finally:
            config.CACHE_DIR = previous

    return decorate
