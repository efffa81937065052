"""Check an ``.npy`` file's header against the file before anything is allocated.

``np.load`` trusts the header: a negative dimension, or a shape that claims 10^12
frames in a small file, ends in a deep traceback or a petabyte allocation attempt.
:func:`check_npy` reads only the header (NumPy's own parser, no unpickling) and checks
that the dimensions are non-negative and that the file holds exactly the bytes they
describe.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .errors import SourceError

__all__ = ["check_npy", "load_npy"]


def check_npy(path: Path, what: str) -> tuple[tuple[int, ...], np.dtype, bool]:
    """Read and check the header of the ``.npy`` file ``path``.

    Args:
        path: the file.
        what: how messages name it (e.g. ``"source (npy-cube)"``).

    Returns:
        ``(shape, dtype, fortran_order)`` as the header declares them.

    Raises:
        SourceError: unreadable file or header, object dtype, a negative dimension, or a
            file smaller than the header describes (truncated, or a header claiming more
            data than the file holds); one line naming ``path``.
    """
    fmt = np.lib.format
    try:
        with open(path, "rb") as handle:
            version = fmt.read_magic(handle)
            reader = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
            if reader is None:
                raise ValueError(f"unsupported .npy format version {version}")
            shape, fortran, dtype = reader(handle, max_header_size=100_000)
            offset = handle.tell()
    except Exception as exc:  # the header parser raises ValueError, SyntaxError, TokenError, ...
        message = " ".join(str(exc).split())[:160]
        raise SourceError(f"{what}: {path} is not a readable .npy file ({message})") from None
    if dtype.hasobject:
        raise SourceError(f"{what}: {path} holds Python objects; expected numbers (no pickles are loaded)")
    if any(int(d) < 0 for d in shape):
        raise SourceError(f"{what}: {path}: its header declares a negative dimension {tuple(shape)}")
    expected = int(np.prod(shape, dtype=object)) * dtype.itemsize
    actual = path.stat().st_size - offset
    if actual < expected:
        raise SourceError(f"{what}: {path} is truncated: its header declares {tuple(shape)} {dtype} "
                          f"= {expected} bytes of data, the file holds {actual}")
    return tuple(int(d) for d in shape), dtype, bool(fortran)


def load_npy(path: Path, what: str, **kwargs: Any) -> np.ndarray:
    """``np.load(path, allow_pickle=False, **kwargs)`` after :func:`check_npy`.

    Raises:
        SourceError: see :func:`check_npy`.
    """
    check_npy(path, what)
    try:
        return np.load(path, allow_pickle=False, **kwargs)
    except (ValueError, OSError, EOFError) as exc:
        raise SourceError(f"{what}: {path} is not a readable .npy file ({exc})") from None
