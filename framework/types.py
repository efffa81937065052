"""Shape checks used at stage boundaries.

Shape vocabulary used across the project (see ``docs/conventions.md``): ``T`` binary
frames, ``G`` groups (virtual exposures), ``P`` pairs, ``H`` rows, ``W`` columns.
"""

from __future__ import annotations

import numpy as np

__all__ = ["check_shape"]


def check_shape(arr: np.ndarray, dims: str, *, name: str, **bound: int) -> dict[str, int]:
    """Check ``arr.shape`` against symbolic ``dims`` such as ``"T H W"`` or ``"T 3 3"``.

    Symbols bind on first use (or come from ``bound``); digits must match exactly.

    Args:
        arr: the array to check.
        dims: space-separated symbols or integers, one per axis.
        name: what the array is, used in the error message.
        **bound: sizes already known for some symbols.

    Returns:
        The bound sizes, so callers can reuse them.

    Raises:
        ValueError: naming ``name``, the axis and the expected size.
    """
    want = dims.split()
    shape = np.shape(arr)
    if len(shape) != len(want):
        raise ValueError(f"{name}: expected shape ({', '.join(want)}), got {shape}")
    sizes = dict(bound)
    for axis, (sym, got) in enumerate(zip(want, shape)):
        expect = int(sym) if sym.isdigit() else sizes.setdefault(sym, got)
        if got != expect:
            raise ValueError(f"{name}: axis {axis} ({sym}) should be {expect}, got shape {shape}")
    return sizes
