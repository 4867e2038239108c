"""One way out for every console script: a table over each ``[project.scripts]`` command and three ways it can end.

Each command gets a missing input, an output under a regular file (``notes.txt/...``, unwritable even for root) and
Ctrl-C once it has started working. Each must exit 1 / 1 / 130 with exactly one line on stderr, ``naka-gs: ...``
(a traceback is a failure), and leave every file it found as it was: no output, no hidden ``.partial`` folder.

The commands run as their installed wrapper runs them (``sys.exit(entrypoint())`` with ``sys.argv`` set), each in a
process of its own forked from one server that imported them all once (an import costs ~3 s a command). The
server never runs torch before it forks. Ctrl-C: the server replaces one function on the command's path by one that
(after running the real one, where ``after``) marks a file and sleeps, and sends SIGINT once the mark is there, so
the signal always lands mid-work, whatever the machine's speed. ``test_the_installed_commands`` (slow) runs the
real executables, imports included.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np
import pytest

from naka_gs_plugin.points.sources import write_ply
from tests.bad_inputs import snapshot
from tests.enhance.test_profile import _write_pairs
from tests.helpers import write_spec

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = dict(
    re.findall(
        r'^(naka-gs-[\w-]+) = "([\w.:]+)"$',
        (REPO / "pyproject.toml").read_text().partition("[project.scripts]")[2].partition("\n[")[0],
        re.M,
    )
)
"""``[project.scripts]``: command -> ``module:entrypoint``."""

SERVER = textwrap.dedent(
    """
    import importlib, json, os, signal, sys, time

    def serve(rows_file, results_file):
        rows = json.loads(open(rows_file).read())
        for module in sorted({row["module"] for row in rows}):
            importlib.import_module(module)
        results = {}
        for row in rows:
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
            if pid == 0:
                return row
            results[row["name"]] = wait(row, pid)
        with open(results_file, "w") as fh:
            json.dump(results, fh)
        return None

    def wait(row, pid):
        deadline, sent = time.monotonic() + row["timeout"], False
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                return {"code": os.waitstatus_to_exitcode(status), "sent": sent}
            if row["hold"] and not sent and os.path.exists(row["started"]):
                os.kill(pid, row["signum"])
                sent = True
            if time.monotonic() > deadline:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return {"code": "timed out", "sent": sent}
            time.sleep(0.02)

    def hold(row):
        module, _, attr = row["hold"].partition(":")
        owner = importlib.import_module(module)
        *path, name = attr.split(".")
        for part in path:
            owner = getattr(owner, part)
        real = getattr(owner, name)

        def held(*args, **kwargs):
            if row["after"]:
                real(*args, **kwargs)
            open(row["started"], "w").close()
            time.sleep(120)
            raise RuntimeError("SIGINT never came")

        setattr(owner, name, held)

    def become(row):
        for fd, path in ((1, row["stdout"]), (2, row["stderr"])):
            os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), fd)
        os.chdir(row["cwd"])
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a suite run with & ignores it)
        if row["hold"]:
            hold(row)
        sys.argv = [row["command"], *row["args"]]
        return importlib.import_module(row["module"]).entrypoint

    row = serve(sys.argv[1], sys.argv[2])
    if row is None:
        sys.exit(0)
    entrypoint = become(row)
    sys.exit(entrypoint())
    """
)


@dataclass
class Row:
    name: str
    command: str
    args: List[str]
    code: int
    names: str
    """A text the one line must hold (the path or the signal)."""
    hold: Optional[str] = None
    """``module:attr`` replaced for the Ctrl-C row."""
    after: bool = True
    """Run the real function first, then wait for the signal."""
    signum: int = signal.SIGINT
    module: str = ""
    cwd: str = ""
    stdout: str = ""
    stderr: str = ""
    started: str = ""
    timeout: float = 120.0


def _lol(root: Path) -> Path:
    """LOL-layout pairs (``train/`` and ``eval/``, ``low/`` + ``high/``) of small noise images."""
    rng = np.random.default_rng(0)
    for split in ("train", "eval"):
        for side, scale in (("low", 20), ("high", 200)):
            (root / split / side).mkdir(parents=True)
            for i in range(2):
                image = (rng.random((40, 48, 3)) * scale).astype(np.uint8)
                cv2.imwrite(str(root / split / side / f"{i}.png"), image)
    return root


def _rows(base: Path, toy: Path) -> List[Row]:
    """Every command's three rows, run in ``base/<row name>/``, with their inputs made there."""
    spec = lambda d: str(write_spec(d, []))  # noqa: E731
    photos = base / "photos"  # process-data's input, shared (never written)
    photos.mkdir()
    for i in range(4):
        (photos / f"{i}.png").write_bytes((toy / "train" / f"{i:04d}.png").read_bytes())
    ply = base / "points.ply"
    rng = np.random.default_rng(0)
    write_ply(ply, rng.normal(size=(400, 3)), (rng.random((400, 3)) * 255).astype(np.uint8))
    pairs = _write_pairs(base / "pairs", n=4)
    lol = _lol(base / "lol")
    naka = ["--enhance.correction", "none"]

    def rows_of(command: str, make) -> List[Row]:
        made = []
        for kind in ("missing", "unwritable", "ctrl_c"):
            folder = base / f"{command}-{kind}"
            folder.mkdir()
            (folder / "notes.txt").write_text("the user's notes")
            row = make(kind, folder)
            row.name, row.command, row.cwd = f"{command}-{kind}", command, str(folder)
            made.append(row)
        return made

    def enhance(kind, d):
        if kind == "missing":
            return Row("", "", ["missing", "--out", "enh"], 1, "missing")
        if kind == "unwritable":
            return Row("", "", [str(toy), "--out", "notes.txt/enh", *naka], 1, "notes.txt")
        hold = "naka_gs_plugin.scripts.enhance:Enhance._write"
        return Row("", "", [str(toy), "--out", "enh", *naka], 130, "Ctrl-C", hold)

    def sim(kind, d):
        if kind == "missing":
            return Row("", "", ["missing.yaml", "--out", "scene"], 1, "missing.yaml")
        if kind == "unwritable":
            return Row("", "", [spec(d), "--out", "notes.txt/scene"], 1, "notes.txt")
        return Row("", "", [spec(d), "--out", "scene"], 130, "Ctrl-C", "naka_gs_plugin.scripts.sim:generate")

    def ppm(kind, d):
        if kind == "missing":
            return Row("", "", ["missing.ply", "--out", "out.ply"], 1, "missing.ply")
        if kind == "unwritable":
            return Row("", "", [str(ply), "--out", "notes.txt/out.ply"], 1, "notes.txt")
        return Row("", "", [str(ply), "--out", "out.ply"], 130, "Ctrl-C", "naka_gs_plugin.scripts.ppm:prepare_points")

    def calibrate(kind, d):
        if kind == "missing":
            return Row("", "", ["missing", "--out", "camera.json"], 1, "missing")
        if kind == "unwritable":
            return Row("", "", [str(pairs), "--out", "notes.txt/camera.json", *naka], 1, "notes.txt")
        hold = "naka_gs_plugin.scripts.calibrate:load_pairs"
        return Row("", "", [str(pairs), "--out", "camera.json", *naka], 130, "Ctrl-C", hold)

    def process_data(kind, d):
        if kind == "missing":
            return Row("", "", ["--data", "missing", "--output-dir", "scene"], 1, "missing")
        args = ["--data", str(photos), *naka]
        if kind == "unwritable":
            return Row("", "", [*args, "--output-dir", "notes.txt/scene"], 1, "notes.txt")
        hold = "naka_gs_plugin.scripts.process_data:refuse_duplicates"
        return Row("", "", [*args, "--output-dir", "scene"], 130, "Ctrl-C", hold)

    def demo(kind, d):
        if kind == "missing":
            return Row("", "", ["--spec", "missing.yaml", "--out", "demo"], 1, "missing.yaml")
        if kind == "unwritable":
            return Row("", "", ["--spec", spec(d), "--out", "notes.txt/demo", "--steps", "0"], 1, "notes.txt")
        # Before the scene is generated: the demo replaces its own outputs in --out and stages none of them.
        hold = "naka_gs_plugin.scripts.demo:generate"
        return Row("", "", ["--spec", spec(d), "--out", "demo", "--steps", "0"], 130, "Ctrl-C", hold, after=False)

    def train_correction(kind, d):
        if kind == "missing":
            return Row("", "", ["--lol", "missing", "--output-dir", "out"], 1, "missing")
        args = ["--lol", str(lol), "--epochs", "1", "--batch-size", "1", "--crop", "32"]
        if kind == "unwritable":
            return Row("", "", [*args, "--output-dir", "notes.txt/out"], 1, "notes.txt")
        hold = "naka_gs_plugin.enhance.correction_train:load_sources"
        return Row("", "", [*args, "--output-dir", "out"], 130, "Ctrl-C", hold)

    makers = {
        "naka-gs-enhance": enhance,
        "naka-gs-sim": sim,
        "naka-gs-ppm": ppm,
        "naka-gs-calibrate": calibrate,
        "naka-gs-process-data": process_data,
        "naka-gs-demo": demo,
        "naka-gs-train-correction": train_correction,
    }
    assert set(makers) == set(SCRIPTS), "a console script without rows here"
    rows = [row for command, make in makers.items() for row in rows_of(command, make)]
    # SIGTERM, which the runner turns into Ctrl-C's clean-up (a staged output's is tests/faults/test_faults_io.py's).
    folder = base / "naka-gs-ppm-sigterm"
    folder.mkdir()
    hold = "naka_gs_plugin.scripts.ppm:prepare_points"
    sigterm = Row("naka-gs-ppm-sigterm", "naka-gs-ppm", [str(ply), "--out", "out.ply"], 143, "SIGTERM", hold)
    sigterm.cwd, sigterm.signum = str(folder), signal.SIGTERM
    rows.append(sigterm)
    for row in rows:
        row.module = SCRIPTS[row.command].partition(":")[0]
        row.stdout, row.stderr = str(base / f"{row.name}.out"), str(base / f"{row.name}.err")
        row.started = str(base / f"{row.name}.started")
    return rows


ROW_NAMES = [f"{command}-{kind}" for command in SCRIPTS for kind in ("missing", "unwritable", "ctrl_c")]
ROW_NAMES.append("naka-gs-ppm-sigterm")


@pytest.fixture(scope="module")
def table(tmp_path_factory, toy_scene):
    """Run every row (one server, one fork each); each row's outcome, output files and snapshots before and after."""
    base = tmp_path_factory.mktemp("console")
    rows = _rows(base, toy_scene)
    kept = [toy_scene, base / "photos", base / "points.ply", base / "pairs", base / "lol"]
    before = {row.name: snapshot([Path(row.cwd), *kept]) for row in rows}
    (base / "rows.json").write_text(json.dumps([asdict(row) for row in rows]))
    env = dict(os.environ, PYTHONPATH=str(REPO), TORCHDYNAMO_DISABLE="1", NAKA_GS_CACHE=str(base / "cache"))
    server = subprocess.run(
        [sys.executable, "-c", SERVER, str(base / "rows.json"), str(base / "results.json")],
        cwd=base,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert server.returncode == 0, server.stdout[-3000:] + server.stderr[-3000:]
    results = json.loads((base / "results.json").read_text())
    after = {row.name: snapshot([Path(row.cwd), *kept]) for row in rows}
    return {row.name: (row, results[row.name], before[row.name], after[row.name]) for row in rows}


@pytest.mark.parametrize("name", ROW_NAMES)
def test_one_way_out(table, name):
    row, result, before, after = table[name]
    err, out = Path(row.stderr).read_text(), Path(row.stdout).read_text()
    report = f"{' '.join([row.command, *row.args])}: exit {result['code']}\nstderr:\n{err}\nstdout:\n{out[-2000:]}"
    assert result["code"] == row.code, report
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("naka-gs: ") and row.names in lines[0], report
    assert "Traceback" not in err + out, report
    assert after == before, report  # the inputs as they were; no output, no hidden .partial folder left
    if row.hold:
        assert result["sent"], report


@pytest.mark.slow  # one process per command (~3 s of imports each)
def test_the_installed_commands(tmp_path):
    """The executables users run (imports included: nothing printed on stderr at import), on a missing input."""
    missing = {
        "naka-gs-enhance": ["missing", "--out", "enh"],
        "naka-gs-sim": ["missing.yaml", "--out", "scene"],
        "naka-gs-ppm": ["missing.ply", "--out", "out.ply"],
        "naka-gs-calibrate": ["missing", "--out", "camera.json"],
        "naka-gs-process-data": ["--data", "missing", "--output-dir", "scene"],
        "naka-gs-demo": ["--spec", "missing.yaml", "--out", "demo"],
        "naka-gs-train-correction": ["--lol", "missing", "--output-dir", "out"],
    }
    assert set(missing) == set(SCRIPTS)
    env = dict(os.environ, TORCHDYNAMO_DISABLE="1", NAKA_GS_CACHE=str(tmp_path / "cache"))
    for command, args in missing.items():
        executable = Path(sys.executable).parent / command
        if not executable.is_file():
            pytest.skip(f"{executable}: not installed (pip install -e .)")
        res = subprocess.run([str(executable), *args], cwd=tmp_path, env=env, capture_output=True, text=True)
        report = f"{command}: exit {res.returncode}\nstderr:\n{res.stderr}"
        lines = res.stderr.splitlines()
        assert res.returncode == 1 and len(lines) == 1 and lines[0].startswith("naka-gs: "), report
        assert "missing" in lines[0], report
    assert not [p.name for p in tmp_path.iterdir() if p.name != "cache"]  # no output made
