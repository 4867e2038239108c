"""Every command in README.md and docs/*.md names a console script (or a ``python -m benchmarks.<name>``) that
exists and options its ``--help`` lists."""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import List, Optional, Tuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
SCRIPTS = PROJECT["scripts"]
METHODS = PROJECT["entry-points"]["nerfstudio.method_configs"]
"""``ns-train`` methods (presets): a span naming one alone is a method, not a command."""
BIN = Path(sys.executable).parent
"""The venv's console scripts (the tests run with its python)."""

NERFSTUDIO = {"ns-train": 1, "ns-eval": 0, "ns-viewer": 0, "ns-render": 1, "ns-export": 1}
"""nerfstudio command -> number of positional words (method, subcommand) that select its ``--help``."""

FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
SPAN = re.compile(r"`([^`]+)`")
ENV = re.compile(r"^(?:[A-Z_][A-Z0-9_]*=\S*\s+)+")
OPTION = re.compile(r"(?<![\w-])--[A-Za-z][\w.-]*")


def command_of(text: str) -> Optional[Tuple[str, List[str]]]:
    """``(script, words)`` of a shell command naming a checked script, else ``None`` (env assignments skipped)."""
    words = ENV.sub("", text.strip()).split()
    if not words:
        return None
    name = words[0].removeprefix(".venv/bin/")
    if name == "python" and words[1:2] == ["-m"] and re.fullmatch(r"benchmarks\.\w+", " ".join(words[2:3])):
        return f"python -m {words[2]}", words[3:]
    if name in METHODS:
        return None
    if re.fullmatch(r"naka-gs-[a-z-]+", name) or (
        name in NERFSTUDIO and (name != "ns-train" or " ".join(words[1:2]) in METHODS)
    ):
        return name, words[1:]
    return None


def doc_commands() -> List[Tuple[str, str, List[str]]]:
    """``(where, script, words)`` of each command in fenced blocks (a line each) and inline code spans."""
    found = []
    for path in DOCS:
        text = path.read_text()
        where = path.relative_to(ROOT)
        for block in FENCE.finditer(text):
            line0 = text.count("\n", 0, block.start(1)) + 1
            for i, line in enumerate(block.group(1).replace("\\\n", " ").splitlines()):
                for part in re.split(r"&&|\|\||[|;]", line.split(" #")[0]):
                    if command := command_of(part):
                        found.append((f"{where}:{line0 + i}", *command))
        prose = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
        for span in SPAN.finditer(prose):
            if command := command_of(span.group(1).replace("\n", " ")):
                found.append((f"{where}:{prose.count(chr(10), 0, span.start()) + 1}", *command))
    return found


COMMANDS = doc_commands()


def normal(option: str) -> str:
    """tyro prints dashes; the docs may write a field's underscores."""
    return option.replace("_", "-")


def help_argv(script: str, words: List[str]) -> Tuple[str, ...]:
    """The command whose ``--help`` lists the options: the script, plus nerfstudio's method or subcommand."""
    return (script, *words[: NERFSTUDIO.get(script, 0)])


@functools.cache
def help_options(argv: Tuple[str, ...]) -> frozenset:
    """Options listed by ``argv --help`` (run once per command, at 80 columns: one column of boxes)."""
    env = dict(os.environ, COLUMNS="80", TORCHDYNAMO_DISABLE="1")
    command = [sys.executable, "-m", argv[0].split()[-1]] if argv[0].startswith("python -m ") else [str(BIN / argv[0])]
    out = subprocess.run(
        [*command, *argv[1:], "--help"], capture_output=True, text=True, env=env, timeout=120, cwd=ROOT
    )
    assert out.returncode == 0, f"{' '.join(argv)} --help failed:\n{out.stderr[-2000:]}"
    # Only the option heads (a box's line starting with a dash): descriptions may name other commands' options.
    heads = [cell.strip().split("  ")[0] for cell in out.stdout.replace("\n", "│").split("│")]
    return frozenset(normal(o) for head in heads if head.startswith("-") for o in OPTION.findall(head))


def test_docs_name_commands():
    """The extraction finds the commands a reader runs first (guards against a parser that finds nothing)."""
    scripts = {script for _, script, _ in COMMANDS}
    assert {"naka-gs-enhance", "python -m benchmarks.grid", "ns-train", "ns-eval"} <= scripts, scripts


@pytest.mark.parametrize("where,script,words", COMMANDS, ids=[f"{w} {s}" for w, s, _ in COMMANDS])
def test_doc_command_parses(where, script, words):
    """The script is installed by pyproject.toml and each ``--option`` written after it is in its ``--help``."""
    if script.startswith("naka-gs-"):
        assert script in SCRIPTS, f"{where}: {script} is not in pyproject.toml [project.scripts]"
    if script.startswith("python -m "):
        module = ROOT / (script.split()[-1].replace(".", "/") + ".py")
        assert module.is_file(), f"{where}: {script}: no {module.relative_to(ROOT)}"
    argv = help_argv(script, words)
    options = [normal(o) for o in OPTION.findall(" ".join(words))]
    known = help_options(argv) if options else frozenset()
    unknown = [option for option in options if option not in known]
    assert not unknown, f"{where}: `{' '.join(argv)}` has no option {', '.join(unknown)} (see its --help)"
