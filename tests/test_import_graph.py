"""The package graph runs one way: every module imports only modules of its own layer or below."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "naka_gs_plugin"

LAYERS = ("helpers", "data", "enhance", "points", "model", "sim and method", "scripts")
"""Bottom to top (``naka_gs_plugin/__init__.py`` describes each)."""
HELPERS = {"cpu", "progress", "metrics", "sheet", "shipped", "errors", "requirements"}
METHOD = {"datamanager", "pipeline", "trainer", "config", "config_check"}
"""The method's wiring, side by side with the simulator above the model."""


def layer(module: str) -> int:
    """Index in :data:`LAYERS` of a ``naka_gs_plugin`` module (dotted name without the package)."""
    top = module.split(".")[0]
    if module == "" or module in HELPERS:
        return 0
    if top == "scripts":
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


def test_the_package_never_imports_the_benchmarks():
    """``benchmarks/`` is not installed: a package module that imported it would break every user's install."""
    graph = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            names += [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            if any(name.split(".")[0] == "benchmarks" for name in names):
                graph.setdefault(str(path.relative_to(PACKAGE)), []).extend(names)
    assert not graph, graph


def test_a_renamed_module_still_loads_old_run_configs():
    """Run configs written before the datamanager moved name ``naka_gs_plugin.data.lowlight_datamanager``."""
    import yaml

    from naka_gs_plugin.datamanager import LowLightDatamanager, LowLightDatamanagerConfig

    old = (
        "!!python/object:naka_gs_plugin.data.lowlight_datamanager.LowLightDatamanagerConfig\n"
        "_target: !!python/name:naka_gs_plugin.data.lowlight_datamanager.LowLightDatamanager ''\n"
    )
    config = yaml.load(old, Loader=yaml.Loader)
    assert type(config) is LowLightDatamanagerConfig and config._target is LowLightDatamanager
    import naka_gs_plugin.datamanager as module

    assert module.__spec__.name == "naka_gs_plugin.datamanager"  # the alias leaves the module's own spec


def test_no_relative_imports():
    """The graph above reads absolute imports only."""
    relative = [
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if any(isinstance(n, ast.ImportFrom) and n.level for n in ast.walk(ast.parse(path.read_text())))
    ]
    assert not relative, relative


def test_console_scripts_live_in_scripts():
    """Every ``[project.scripts]`` entry is ``naka-gs-<name> = naka_gs_plugin.scripts.<name>:entrypoint`` and its
    module holds the dataclass ``<Name>`` with ``main()`` (the naming scheme of ``naka_gs_plugin/scripts``)."""
    import dataclasses
    import importlib

    tomllib = pytest.importorskip("tomllib", reason="Python < 3.11 has no tomllib; CI runs this on 3.11")

    pyproject = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())
    entries = pyproject["project"]["scripts"]
    wrong = []
    for name, target in entries.items():
        stem = name.removeprefix("naka-gs-").replace("-", "_")
        if target != f"naka_gs_plugin.scripts.{stem}:entrypoint":
            wrong.append(f"{name} = {target}")
            continue
        module = importlib.import_module(f"naka_gs_plugin.scripts.{stem}")
        cls = getattr(module, "".join(part.title() for part in stem.split("_")), None)
        if not (dataclasses.is_dataclass(cls) and callable(getattr(cls, "main", None))):
            wrong.append(f"{name}: no dataclass {stem.title().replace('_', '')} with main() in scripts/{stem}.py")
    modules = {p.stem for p in (PACKAGE / "scripts").glob("*.py")} - {"__init__"}
    orphans = modules - {n.removeprefix("naka-gs-").replace("-", "_") for n in entries}
    assert not wrong and not orphans, (wrong, orphans)


def test_gpu_side_modules_import_without_nerfstudio():
    """The parity harness, cpu-fast and the correction trainer run on a GPU machine that has no nerfstudio."""
    import subprocess
    import sys

    block = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'nerfstudio':\n"
        "            raise ImportError(name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import benchmarks.cuda_parity, naka_gs_plugin.scripts.train_correction\n"
        "import naka_gs_plugin.model.rasterize_cpu_fast\n"
    )
    proc = subprocess.run([sys.executable, "-c", block], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
