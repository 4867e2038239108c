"""The docs stay true: every command in README.md and the guides (docs/*.md) names a console script (or a
``python -m benchmarks.<name>``) that exists and options its ``--help`` lists; every figure in the README's tables
links the record it comes from (docs/records/), which exists and is headed by its question, answer, command, commit
and machine; the README and the guides stay short; every relative link resolves.

The records are history: their commands ran on the tree of their date, so they are not checked against today's
``--help``."""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import List, Optional, Tuple

import pytest

tomllib = pytest.importorskip("tomllib", reason="Python < 3.11 has no tomllib; CI runs these on 3.11")

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
"""README and the guides (the records in docs/records/ are history, see the module's docstring)."""
RECORDS = ROOT / "docs" / "records"
README_MAX_LINES, GUIDE_MAX_LINES = 200, 300
HEADER_FIELDS = ("Question", "Answer", "Command", "Commit", "Machine")
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


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
TABLE_ROW = re.compile(r"^\|(?!\s*-{3})(.*)\|\s*$")
COMMIT = re.compile(r"`[0-9a-f]{7,40}`")
MACHINE = re.compile(r"\b(AMD|Intel|NVIDIA|Apple|ARM|Ampere|Graviton)\b")


def record_files() -> List[Path]:
    return sorted(p for p in RECORDS.glob("*.md") if p.name != "README.md")


def figure_rows(text: str) -> List[Tuple[int, str]]:
    """``(line, row)`` of each table row holding a digit, header rows and fenced blocks left out."""
    prose = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    lines = prose.splitlines()
    rows = []
    for i, line in enumerate(lines):
        if not TABLE_ROW.match(line) or not re.search(r"\d", line):
            continue
        if i + 1 < len(lines) and re.match(r"^\|\s*-{3}", lines[i + 1]):
            continue  # a header row
        rows.append((i + 1, line))
    return rows


def test_readme_figures_link_an_existing_record_with_commit_and_machine():
    """Each README table row with a number links a record file in docs/records/ that exists; a row of ours (not a
    published figure) also names the commit and the machine of its run."""
    rows = figure_rows((ROOT / "README.md").read_text())
    assert len(rows) >= 5, rows  # the results tables are found
    for line, row in rows:
        records = [t for t in LINK.findall(row) if t.split("#")[0].startswith("docs/records/")]
        assert records, f"README.md:{line}: a figure without a link to its record in docs/records/: {row}"
        for target in records:
            path = ROOT / target.split("#")[0]
            assert path.is_file() and path.suffix == ".md", f"README.md:{line}: no record {target}"
        if "published" not in row:
            assert COMMIT.search(row), f"README.md:{line}: the row names no commit (`abc1234`): {row}"
            assert MACHINE.search(row), f"README.md:{line}: the row names no machine: {row}"


def test_figure_rows_detects_a_row_without_its_record():
    """The check above sees a bare figure row, and the header and separator rows are not figures."""
    text = "| | PSNR |\n|---|---|\n| naka-gs 2026 | 23.30 |\n| x | 1 [r](docs/records/a.md) |\n"
    rows = figure_rows(text)
    assert [line for line, _ in rows] == [3, 4]
    assert not [t for t in LINK.findall(rows[0][1]) if t.startswith("docs/records/")]


def test_readme_and_guides_stay_short():
    """A README read in five minutes, guides at most a few pages; the records hold the history."""
    readme = (ROOT / "README.md").read_text().splitlines()
    assert len(readme) <= README_MAX_LINES, f"README.md has {len(readme)} lines (at most {README_MAX_LINES})"
    guides = sorted((ROOT / "docs").glob("*.md"))
    assert {"design.md", "cpu.md", "cuda.md", "real-scenes.md"} <= {p.name for p in guides}
    for path in guides:
        n = len(path.read_text().splitlines())
        assert n <= GUIDE_MAX_LINES, f"{path.relative_to(ROOT)} has {n} lines (at most {GUIDE_MAX_LINES})"


@pytest.mark.parametrize("path", record_files(), ids=[p.name for p in record_files()])
def test_record_is_headed_by_its_question_answer_command_commit_and_machine(path):
    """Each record opens with a title and the five fields, each non-empty, in this order, and is in the index."""
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# "), f"{path.name}: no title"
    fields = [re.match(r"^- \*\*(\w+)\*\*: (\S.*)$", line) for line in lines[1:12]]
    found = [m.group(1) for m in fields if m]
    assert tuple(found) == HEADER_FIELDS, f"{path.name}: header fields {found}, expected {list(HEADER_FIELDS)}"
    assert re.match(r"^\d{4}-\d{2}-\d{2}-[a-z0-9-]+\.md$", path.name), f"{path.name}: not YYYY-MM-DD-topic.md"
    assert f"({path.name})" in (RECORDS / "README.md").read_text(), f"{path.name} is not listed in records/README.md"


def slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_relative_links_resolve():
    """Every relative link in README.md and docs/**/*.md names a file that exists (and a heading of it, if an
    anchor is given): moved text keeps its images, experiments and records."""
    broken = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        prose = FENCE.sub("", path.read_text())
        for target in LINK.findall(prose):
            if re.match(r"[a-z][a-z+.-]*:", target):
                continue
            file, _, anchor = target.partition("#")
            dest = (path.parent / file).resolve() if file else path
            where = f"{path.relative_to(ROOT)}: {target}"
            if not dest.exists():
                broken.append(f"{where} (no such file)")
            elif anchor and dest.suffix == ".md":
                heads = {slug(h) for h in re.findall(r"^#+ (.*)$", dest.read_text(), re.M)}
                if anchor not in heads:
                    broken.append(f"{where} (no such heading)")
    assert not broken, "broken links:\n" + "\n".join(broken)
