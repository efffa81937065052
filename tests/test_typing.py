"""The public surface passes ``mypy --strict``; the package's other mypy errors stay under a ceiling.

The public surface: photonpano/__init__.py, api.py, records.py, stages.py; the ceiling is
``CEILING`` in ``.ci/typecheck.py``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_public_surface_passes_mypy_strict():
    pytest.importorskip("mypy", reason="mypy is not installed (pip install -e '.[test]')")
    done = subprocess.run([sys.executable, str(ROOT / ".ci" / "typecheck.py"), "--strict-only"],
                          capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Success: no issues found in 4 source files" in done.stdout


def _typecheck_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("photonpano_ci_typecheck", ROOT / ".ci" / "typecheck.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_mypy_error_ceiling_fails_above_and_asks_to_lower_below():
    typecheck = _typecheck_module()
    assert typecheck.ceiling_check(typecheck.CEILING) == (
        True, f"typecheck: {typecheck.CEILING} mypy errors (the ceiling)")
    within, line = typecheck.ceiling_check(11, ceiling=10)
    assert not within and "more than the ceiling of 10" in line
    within, line = typecheck.ceiling_check(7, ceiling=10)
    assert within and "lower CEILING in .ci/typecheck.py to 7" in line
