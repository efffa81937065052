"""Paths and small helpers shared by test modules (import as ``from testdata import ...``).

Kept out of ``conftest.py``: several folders have a conftest, and ``from conftest import``
would pick whichever was imported first.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

DATA = Path(__file__).parent / "data"
"""Folder of the test data (see data/SOURCES.md)."""


def packed_cube(capture) -> np.ndarray:
    """Return the bit-packed (T, H, W/8) cube of a simulated capture."""
    return np.asarray(capture.cube)
