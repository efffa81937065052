"""The test suite never installs anything into the environment it runs in (issue 29)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).parents[2]


RUNNERS = {"run", "Popen", "call", "check_call", "check_output", "system", "main", "run_subprocess", "spawnv"}
"""Functions that start a program (subprocess's, ``os.system``, ``pip.main``, the suite's own helper)."""


def installing_calls(path: Path) -> list[int]:
    """Lines of ``path`` starting a program whose string arguments name ``pip`` (or ``ensurepip``) and ``install``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        name = getattr(node.func, "attr", getattr(node.func, "id", None)) if isinstance(node, ast.Call) else None
        if name not in RUNNERS:
            continue
        words = {w for arg in ast.walk(node) if isinstance(arg, ast.Constant) and isinstance(arg.value, str)
                 for w in arg.value.replace("-", " ").split()}
        if words & {"pip", "ensurepip", "pip3"} and words & {"install", "develop"}:
            found.append(node.lineno)
    return found


def test_the_scanner_finds_a_pip_install(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text('import subprocess, sys\nsubprocess.run([sys.executable, "-m", "pip", "install", "-e", "x"])\n'
                      'print("pip install x")\nos.system("pip3 install y")\n')
    assert installing_calls(sample) == [2, 4]  # a message naming the command is not a call of it


def test_no_test_calls_pip_install():
    """The example plugin is found through sys.path and a temporary .dist-info (tests/test_example_plugin.py)."""
    files = [*ROOT.joinpath("tests").rglob("*.py"), *ROOT.joinpath("examples").rglob("tests/*.py")]
    offenders = {str(f.relative_to(ROOT)): lines for f in files for lines in [installing_calls(f)] if lines}
    assert not offenders, offenders
