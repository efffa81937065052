"""examples/notebook.ipynb runs top to bottom in a Jupyter kernel (nbclient) and shows what it says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "examples" / "notebook.ipynb"


@pytest.mark.slow
def test_example_notebook_runs_and_shows_the_result(tmp_path):
    nbformat = pytest.importorskip("nbformat", reason="nbformat is not installed (pip install -e '.[test]')")
    nbclient = pytest.importorskip("nbclient", reason="nbclient is not installed (pip install -e '.[test]')")
    pytest.importorskip("ipykernel", reason="ipykernel is not installed (pip install -e '.[test]')")
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not cell.get("outputs") for cell in notebook.cells if cell.cell_type == "code")  # stored clean
    nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    stderr = "".join(o.get("text", "") for o in outputs if o.output_type == "stream" and o.name == "stderr")
    assert "IProgress not found" not in stderr and "Warning" not in stderr, stderr[-2000:]
    # the RunResult cell shows the compact HTML summary with its thumbnail
    html = [o.data["text/html"] for o in outputs if o.output_type == "execute_result" and "text/html" in o.data]
    assert len(html) == 1 and "photonpano RunResult" in html[0] and "data:image/png;base64," in html[0]
    assert re.search(r'class="status ok"', html[0]), html[0][:500]
    # the printed figures: every frame has a homography, the error is that of a good run
    stdout = "".join(o.get("text", "") for o in outputs if o.output_type == "stream" and o.name == "stdout")
    assert "homographies (3000, 3, 3)" in stdout
    rmse = float(re.search(r"trajectory RMSE ([0-9.]+) px", stdout).group(1))
    psnr = float(re.search(r"panorama PSNR ([0-9.]+) dB", stdout).group(1))
    assert rmse < 0.5 and psnr > 25, stdout
    # and the trajectory figure
    assert any("image/png" in o.get("data", {}) for o in outputs if o.output_type == "display_data")
    assert not list(tmp_path.iterdir())  # nothing written: the run stays in memory
