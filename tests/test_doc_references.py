"""Code points at doc files, never at a section of one by its title.

The comments and docstrings of naka_gs_plugin/, benchmarks/, scripts/ and tests/ (and the whole text of their
shell and YAML files) cite measurements by a record file (records/<date>-<topic>.md, or with docs/ in front) or
by a whole guide (docs/<guide>.md). Sections move when the docs are reorganised (the dated studies left the
guides for docs/records/), so a citation of a section by its title or anchor goes stale silently. Here every
cited docs/ or records/ markdown path must exist (records/ relative to docs/, docs/ to the repository root), and
a path followed by a quoted title, an ``#anchor`` or the word "section" fails unless that heading exists in the
file (titles compared as GitHub anchors: lowercase, spaces to ``-``, punctuation dropped).

Python code strings (messages, test data) are not scanned: only comments and docstrings are citations."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path
from typing import Iterator, List, Tuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCANNED_DIRS = ("naka_gs_plugin", "benchmarks", "scripts", "tests")
SUFFIXES = (".py", ".sh", ".yaml", ".yml")

DOC_PATH = re.compile(r"(?<![\w./-])(?:\.\./)*(?P<path>(?:docs|records)/[\w./-]*\.md)(?!\w)")
"""A cited doc: a markdown path starting docs/ or records/ (not one inside another folder, such as ../shared/)."""
SECTION = re.compile(
    r"""\#(?P<anchor>[\w-]+)"""
    r"""|\s*,\s*(?:"(?P<dq>[^"]+)"|“(?P<cq>[^”]+)”|'(?P<sq>[^'\n]+)')"""
    r"""|\s*,?\s*(?P<word>section\b|§)"""
    r"""|,\s+(?P<bare>[A-Za-z][\w'-]*(?:[ \t]+[\w'-]+){0,3})[ \t]*\)""",
    re.I,
)
"""What follows a cited path when it names a section: ``#anchor``, ``, "Title"`` (also curly or single quotes, the
title possibly wrapped over lines), the word "section", or a short unquoted title that closes the parenthesis
(``, Levers)``)."""
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)
FENCE = re.compile(r"^\s*(```|~~~).*?^\s*\1", re.S | re.M)
HTML_ANCHOR = re.compile(r"""<a\s+(?:name|id)\s*=\s*["']([^"']+)["']""", re.I)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading (link text kept, punctuation dropped, spaces to ``-``)."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    return re.sub(r"[^\w\- ]", "", " ".join(text.split()).lower()).replace(" ", "-")


def anchors(md: Path) -> set:
    """The anchors of a markdown file's headings (repeats numbered as GitHub does) and its explicit HTML anchors."""
    text = md.read_text()
    seen: dict = {}
    out = set(HTML_ANCHOR.findall(text))
    for heading in HEADING.findall(FENCE.sub("", text)):
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def resolve(path: str, root: Path) -> Path:
    """A cited path on disk: ``records/...`` under docs/, ``docs/...`` under the repository root."""
    return root / "docs" / path if path.startswith("records/") else root / path


def citation_texts(source: str, suffix: str) -> Iterator[Tuple[int, str]]:
    """(first line, text) of each part of a file that cites: a Python file's docstrings (every string statement)
    and comment blocks (consecutive comment lines joined, so a title wrapped over lines stays one); any other
    file whole, its lines' leading ``#`` dropped."""
    if suffix != ".py":
        yield 1, re.sub(r"^[ \t]*#+ ?", "", source, flags=re.M)
        return
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            yield node.lineno, node.value.value
    block: List[str] = []
    start = last = 0
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        line = tok.start[0]
        if block and line != last + 1:
            yield start, "\n".join(block)
            block = []
        if not block:
            start = line
        block.append(tok.string.lstrip("#").strip())
        last = line
    if block:
        yield start, "\n".join(block)


def bad_references(text: str, root: Path = ROOT) -> List[Tuple[int, str]]:
    """(line offset in ``text``, problem) for each cited doc path that does not exist or names a section that is
    not a heading of it."""
    problems = []
    for m in DOC_PATH.finditer(text):
        path = m.group("path")
        where = text.count("\n", 0, m.start())
        dest = resolve(path, root)
        if not dest.is_file():
            problems.append((where, f"{path}: no such file"))
            continue
        s = SECTION.match(text, m.end())
        if not s:
            continue
        if s.group("word"):
            problems.append((where, f"{path}: names a section ({s.group(0).strip()!r}); cite the record file"))
            continue
        quoted = s.group("dq") or s.group("cq") or s.group("sq") or s.group("bare")
        title = s.group("anchor") or " ".join(quoted.split())
        if slug(title) not in anchors(dest):
            problems.append((where, f"{path}: no heading {title!r} (sections moved to docs/records/: cite the file)"))
    return problems


def scanned_files() -> List[Path]:
    return sorted(
        p
        for d in SCANNED_DIRS
        for p in (ROOT / d).rglob("*")
        if p.suffix in SUFFIXES and p.is_file() and "__pycache__" not in p.parts
    )


def test_code_cites_doc_files_that_exist_and_no_missing_section():
    files = scanned_files()
    assert any(p.name == "config.py" for p in files) and any(p.suffix == ".sh" for p in files)
    broken = []
    for path in files:
        for start, text in citation_texts(path.read_text(), path.suffix):
            for offset, problem in bad_references(text):
                broken.append(f"{path.relative_to(ROOT)}:{start + offset}: {problem}")
    assert not broken, "stale doc references in code:\n" + "\n".join(broken)


@pytest.fixture
def docs_tree(tmp_path: Path) -> Path:
    (tmp_path / "docs" / "records").mkdir(parents=True)
    (tmp_path / "docs" / "cpu.md").write_text("# The CPU paths\n\n## How to check it\n\n```\n# not a heading\n```\n")
    (tmp_path / "docs" / "records" / "2026-11-27-levers.md").write_text("# Levers tried\n\n## Notes\n\n## Notes\n")
    return tmp_path


@pytest.mark.parametrize(
    "text",
    [
        "see docs/cpu.md.",
        "(records/2026-11-27-levers.md)",
        "(docs/records/2026-11-27-levers.md; and docs/cpu.md, which the tests check on a CPU and a GPU)",
        "(docs/cpu.md, How to check it)",
        'docs/cpu.md, "How to check it"',
        "docs/cpu.md#how-to-check-it",
        "records/2026-11-27-levers.md#notes-1",
        "../shared/data/x/README.md, and ``method-facts.md`` section 5",
    ],
)
def test_scanner_passes_files_and_existing_headings(docs_tree, text):
    assert bad_references(text, docs_tree) == []


@pytest.mark.parametrize(
    "text",
    [
        "(docs/real-scenes.md)",
        "(records/2026-11-27-fewer-full-size-steps.md)",
        '(docs/cpu.md, "Fewer full-size steps")',
        '(docs/cpu.md, "Fewer\n    full-size steps")',
        "(docs/cpu.md, “Levers”)",
        "(docs/cpu.md, 'The 8-wide kernels shipped')",
        "docs/cpu.md#levers",
        "docs/cpu.md#not-a-heading",
        "docs/cpu.md section 3",
        "(docs/cpu.md, capture tone).",
        "protocol: docs/cpu.md, Levers).",
    ],
)
def test_scanner_fails_a_planted_bad_reference(docs_tree, text):
    assert len(bad_references(text, docs_tree)) == 1


def test_scanner_reads_comments_and_docstrings_not_code_strings(docs_tree):
    source = (
        '"""Module doc (docs/cpu.md, "Gone")."""\n'
        "X = 1\n"
        '"""Attribute doc: docs/missing.md."""\n'
        "# a comment block whose title wraps (docs/cpu.md,\n"
        '# "Also gone").\n'
        'MESSAGE = "test data, not a citation: docs/cpu.md, \\"Gone\\""\n'
        "y = 2  # docs/cpu.md is fine\n"
    )
    found = [
        (start + offset, problem)
        for start, text in citation_texts(source, ".py")
        for offset, problem in bad_references(text, docs_tree)
    ]
    assert sorted(line for line, _ in found) == [1, 3, 4]
    assert [p for p in ("Gone", "missing.md", "Also gone") if any(p in problem for _, problem in found)] == [
        "Gone",
        "missing.md",
        "Also gone",
    ]
    shell = "#!/bin/bash\n# The protocol (docs/cpu.md,\n#   'Gone'): runs\necho docs/records/2026-11-27-levers.md\n"
    assert [
        (s + o, p.split(":")[0]) for s, t in citation_texts(shell, ".sh") for o, p in bad_references(t, docs_tree)
    ] == [(2, "docs/cpu.md")]
