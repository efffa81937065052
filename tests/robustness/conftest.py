"""Fixtures of the hostile-input suite."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="session")
def small_cube(tmp_path_factory):
    """A bit-packed (400, 32, 8) uint8 .npy photon cube of random binary frames."""
    path = tmp_path_factory.mktemp("cube") / "cube.npy"
    frames = np.random.default_rng(0).random((400, 32, 64)) < 0.3
    np.save(path, np.packbits(frames, axis=-1))
    return path
