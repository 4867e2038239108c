"""The package graph runs one way: every module imports only modules of its own layer or below."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "naka_gs_plugin"

FLOORS = ("helpers", "data", "run", "enhance", "points", "model", "sim", "method", "scripts")
"""Bottom to top (``naka_gs_plugin/__init__.py`` describes each): a module imports only its own floor and those
below, and on the method's floor only the files below it in :data:`METHOD`."""
HELPERS = {"cpu", "progress", "metrics", "sheet", "shipped", "errors", "requirements"}
METHOD = ("datamanager", "pipeline", "trainer", "config")
"""The method's wiring, one file above the other: the presets (``config``) are the roof."""


def rank(module: str) -> tuple:
    """Where a ``naka_gs_plugin`` module (dotted name without the package) stands: (floor, place on the floor)."""
    top = module.split(".")[0]
    if module == "" or module in HELPERS:
        return (0, 0)
    if module in METHOD:
        return (FLOORS.index("method"), METHOD.index(module))
    if top in FLOORS[1:]:
        return (FLOORS.index(top), 0)
    raise AssertionError(f"naka_gs_plugin.{module} has no floor: place it in tests/test_import_graph.py")


def imports() -> Dict[str, Set[str]]:
    """Every module's ``naka_gs_plugin`` imports, top-level and inside functions (dotted, without the package); an
    import of a package counts as an import of its ``__init__``, ``from package import module`` as one of that
    module."""
    modules = set()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        modules.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    graph = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names: List[str] = []
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            for name in names:
                if name.split(".")[0] != "naka_gs_plugin":
                    continue
                dotted = name.partition(".")[2]
                if dotted in modules and dotted != module:
                    found.add(dotted)
        graph[module] = found
    return graph


def circles(graph: Dict[str, Set[str]]) -> List[List[str]]:
    """The graph's strongly connected components of more than one module (Tarjan's algorithm)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    found: List[List[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for dep in graph.get(node, ()):
            if dep not in index:
                visit(dep)
                low[node] = min(low[node], low[dep])
            elif dep in stack:
                low[node] = min(low[node], index[dep])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_file_level_import_graph_has_no_circle():
    """Every import statement, lazy ones included, file by file: no two modules import each other, however far
    round."""
    assert not circles(imports()), circles(imports())


def test_circles_finds_a_circle_of_three():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_module_imports_a_floor_above_it():
    """Nothing runs back up: not to a higher floor, and on the method's floor not to a file above (the trainer
    never imports the presets, the pipeline never the trainer)."""
    upward = [
        f"naka_gs_plugin.{module} {rank(module)} imports naka_gs_plugin.{dep} {rank(dep)}"
        for module, deps in imports().items()
        for dep in sorted(deps)
        if rank(dep) > rank(module) and not (module == "" or dep.startswith(module + "."))
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


def test_no_module_is_over_700_lines():
    """Rooms that say what they are: a module past 700 lines holds more than one idea, split it."""
    long = {
        str(path.relative_to(PACKAGE.parent)): n
        for path in sorted(PACKAGE.rglob("*.py"))
        if (n := len(path.read_text().splitlines())) > 700
    }
    assert not long, long
