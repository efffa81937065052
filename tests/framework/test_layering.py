"""The core (``framework/``) depends on no built-in plugin: it reaches them through the plugin host."""

import ast
from pathlib import Path

FRAMEWORK = Path(__file__).parents[2] / "framework"
ALLOWED = {"cli_tools.py"}
"""Modules still importing a built-in plugin (``convert`` calls the swissspad-bin converter; issue 12)."""


def plugin_imports(path: Path) -> list[str]:
    """Return the ``photonpano.plugins...`` modules that ``path`` imports (at any depth)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
            [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
        found += [n for n in names if n == "photonpano.plugins" or n.startswith("photonpano.plugins.")]
    return found


def test_plugin_imports_are_found():
    """The scanner sees a lazy import inside a function (so the next test can fail)."""
    sample = FRAMEWORK.parent / "plugins" / "sources" / "swissspad.py"
    assert "photonpano.plugins.sources._swissspad_sensor" in plugin_imports(sample)


def test_framework_imports_no_built_in_plugin():
    """No module under framework/ (outside ``ALLOWED``) imports ``photonpano.plugins``."""
    offenders = {str(p.relative_to(FRAMEWORK)): plugin_imports(p) for p in sorted(FRAMEWORK.rglob("*.py"))
                 if str(p.relative_to(FRAMEWORK)) not in ALLOWED}
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"framework modules importing built-in plugins: {offenders}"


def framework_imports(path: Path) -> set[str]:
    """Return the framework modules (paths relative to framework/, no suffix) that ``path`` imports, lazily too."""
    package = path.relative_to(FRAMEWORK).parent.parts
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = list(package[:len(package) - node.level + 1]) + (node.module.split(".") if node.module else [])
            found |= {"/".join(base + [a.name]) for a in node.names} | {"/".join(base)}
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
            found |= {n.removeprefix("photonpano.").replace(".", "/") for n in names if n.startswith("photonpano.")}
    return found


def test_no_two_framework_modules_import_each_other():
    """No import cycle of two modules (e.g. cli <-> cli_tools, spec <-> spec_paths), lazy imports included."""
    modules = {str(p.relative_to(FRAMEWORK).with_suffix("")): p for p in FRAMEWORK.rglob("*.py")}
    graph = {name: framework_imports(path) & set(modules) - {name} for name, path in modules.items()}
    assert "cli_base" in graph["cli_tools"] and "spec_defaults" in graph["spec_paths"]  # the scanner sees them
    pairs = sorted({tuple(sorted((a, b))) for a, targets in graph.items() for b in targets if a in graph[b]})
    assert not pairs, f"modules importing each other: {pairs}"


MAX_LINES = 400
"""Longest module allowed under framework/ and plugins/ (issue 31: split along real seams)."""


def test_no_module_is_over_the_line_limit():
    """No Python module under framework/ or plugins/ is longer than ``MAX_LINES`` lines."""
    root = FRAMEWORK.parent
    lengths = {str(p.relative_to(root)): len(p.read_text().splitlines())
               for folder in ("framework", "plugins") for p in (root / folder).rglob("*.py")}
    assert len(lengths) > 100 and max(lengths.values()) > MAX_LINES / 2  # the scan sees the tree
    over = {name: n for name, n in sorted(lengths.items()) if n > MAX_LINES}
    assert not over, f"modules over {MAX_LINES} lines: {over}"


def test_the_level_loop_knows_nothing_of_binning():
    """levels.py imports nothing of the photon budget; binning is a scheme wrapper's (schemes/binned.py)."""
    imports = framework_imports(FRAMEWORK / "levels.py")
    assert "schemes" in imports  # the scanner sees the level loop's imports
    assert not {name for name in imports if name.split("/")[0] in ("budget", "imaging")}, imports
    assert "binning" not in (FRAMEWORK / "levels.py").read_text()
