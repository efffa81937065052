"""Shared fixtures: plugin hosts and small simulated captures with ground truth."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    """Keep OpenCV on one thread: the CI machine has two cores, shared."""
    import cv2

    cv2.setNumThreads(1)


@pytest.fixture(autouse=True, scope="session")
def _temporary_files_in_pytests_folder(tmp_path_factory):
    """Send what the code under test writes to the temporary folder into pytest's own (cleaned by pytest).

    A plugin failure's traceback file (:func:`photonpano.faults.plugin_failure`) and Dask's
    scratch space otherwise stay in the system's ``/tmp`` after every run of the suite;
    ``TMPDIR`` carries the folder to the processes the tests start.
    """
    import tempfile

    folder = str(tmp_path_factory.mktemp("tmp"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TMPDIR", folder)
        patch.setattr(tempfile, "tempdir", folder)
        yield


@pytest.fixture
def host():
    """A plugin host with every installed plugin (built-ins come through entry points)."""
    from photonpano.host import PluginHost

    return PluginHost()


@pytest.fixture
def bare_host(monkeypatch):
    """A plugin host with no plugins loaded; register what a test needs."""
    from photonpano.host import PluginHost

    monkeypatch.setenv("PHOTONPANO_DISABLE_PLUGIN_AUTOLOAD", "1")
    return PluginHost()


@pytest.fixture(scope="session")
def tiny_capture():
    """2 400 binary frames of 128x248 panning across the bundled photo (flux 0.5)."""
    from photonpano.plugins.sources.simulate import SimulateConfig

    return SimulateConfig(frames=2400, height=128, width=248, flux=0.5, vibration_px=2.0).build()
