"""The package graph runs one way: every module imports only modules of its own layer or below."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set

PACKAGE = Path(__file__).resolve().parents[1] / "naka_gs_plugin"

LAYERS = ("helpers", "data", "enhance", "points", "model", "sim and method", "scripts and benches")
"""Bottom to top (``naka_gs_plugin/__init__.py`` describes each)."""
HELPERS = {"cpu", "progress", "metrics", "sheet"}
METHOD = {"data.lowlight_datamanager", "pipeline", "trainer", "config"}
"""The method's wiring, side by side with the simulator above the model."""
SCRIPTS = {"process_data", "demo"}


def layer(module: str) -> int:
    """Index in :data:`LAYERS` of a ``naka_gs_plugin`` module (dotted name without the package)."""
    top = module.split(".")[0]
    if module == "" or module in HELPERS:
        return 0
    if module in SCRIPTS or top == "bench" or module.endswith(".cli"):
        return 6
    if module in METHOD or top == "sim":
        return 5
    if top in ("data", "enhance", "points", "model"):
        return LAYERS.index(top)
    raise AssertionError(f"naka_gs_plugin.{module} has no layer: place it in tests/test_import_graph.py")


def imports() -> Dict[str, Set[str]]:
    """Every module's ``naka_gs_plugin`` imports, top-level and inside functions (dotted, without the package)."""
    graph = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names: List[str] = []
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            found |= {name.partition(".")[2] for name in names if name.split(".")[0] == "naka_gs_plugin"}
        graph[module] = found
    return graph


def test_no_module_imports_a_layer_above_it():
    upward = [
        f"naka_gs_plugin.{module} ({LAYERS[layer(module)]}) imports naka_gs_plugin.{dep} ({LAYERS[layer(dep)]})"
        for module, deps in imports().items()
        for dep in sorted(deps)
        if layer(dep) > layer(module)
    ]
    assert not upward, "imports against the package order:\n" + "\n".join(upward)


def test_no_relative_imports():
    """The graph above reads absolute imports only."""
    relative = [
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if any(isinstance(n, ast.ImportFrom) and n.level for n in ast.walk(ast.parse(path.read_text())))
    ]
    assert not relative, relative
