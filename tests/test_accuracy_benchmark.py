"""benchmarks/accuracy.py writes its table into the docs between markers (issue 10)."""

from pathlib import Path

import pytest
from capture_helpers import load_benchmark


def _module():
    return load_benchmark("accuracy")


def test_the_table_replaces_only_the_text_between_the_markers(tmp_path):
    """Text around the markers is kept; the old table is replaced; a file without markers is refused."""
    bench = _module()
    doc = tmp_path / "accuracy.md"
    start, end = bench.START.format("accuracy-table"), bench.END.format("accuracy-table")
    doc.write_text(f"intro\n{start}\nold table\n{end}\noutro\n")
    row = {"regime": "fast-pan", "variant": "default", "frames": 12000, "bar": 0.5, "rmse": [0.5, 0.3, 0.24],
           "psnr": 32.0, "psnr_true": 32.1, "gap": 0.1, "group_size": 84, "binning": 2, "status": "ok",
           "warnings": [], "seconds": 113.0, "cpu_s": 40.0}
    bench.write_table(doc, bench.markdown([row]), "python benchmarks/accuracy.py")
    text = doc.read_text()
    assert text.startswith("intro\n") and text.endswith("outro\n") and "old table" not in text
    assert "| fast-pan | 12000 | default | 0.500, 0.300, **0.240** | 0.5 |" in text
    assert "| 84 (2) | ok |" in text
    doc.write_text("no markers")
    with pytest.raises(SystemExit, match="markers"):
        bench.write_table(doc, "table", "cmd")
    assert set(bench.REGIMES) >= {"fast-pan", "dark-flux", "dark-scene", "rotation-zoom"}


def test_the_stamp_names_no_path_of_the_machine(tmp_path):
    """Absolute paths in the stamped command become file names (outside the repository) or repo-relative."""
    bench = _module()
    root = Path(__file__).parents[1]
    assert bench.portable_command(f"python benchmarks/accuracy.py --photo /data/shared/madison1.png --write "
                                  f"{root / 'docs' / 'accuracy.md'} --frames=6000 --out=/tmp/x/run") == (
        "python benchmarks/accuracy.py --photo madison1.png --write docs/accuracy.md --frames=6000 --out=run")
    doc = tmp_path / "doc.md"
    doc.write_text(f"{bench.START.format('t')}\n{bench.END.format('t')}\n")
    bench.write_table(doc, "table", "python benchmarks/accuracy.py --photo /work/shared/data/photos/x.jpg", "t")
    assert "--photo x.jpg`" in doc.read_text() and "/work/" not in doc.read_text()
