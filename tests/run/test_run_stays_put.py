"""A run stays in its folder, and nothing in it blocks: names that would leave ``--output-dir`` are refused, a run
claim that is not a regular file is named as such, and a path too long for the system is one line."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from nerfstudio.scripts import train as ns_train

from naka_gs_plugin.run.claim import RUN_CLAIM
from tests.helpers import tiny_run_config


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def _train_exits(config, timeout: float = 120.0) -> str:
    """ns-train's main on ``config`` in a thread that must end within ``timeout`` (a block fails the test);
    the SystemExit's line."""
    result: dict = {}

    def target() -> None:
        try:
            ns_train.main(config)
        except SystemExit as exc:
            result["code"] = exc.code
        except BaseException as exc:  # reported below
            result["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), "ns-train blocked"
    assert "error" not in result, result.get("error")
    return str(result.get("code"))


@pytest.mark.parametrize(
    "flag, field, value",
    [
        ("--timestamp", "timestamp", "../../../../x"),
        ("--timestamp", "timestamp", "/tmp/elsewhere"),
        ("--experiment-name", "experiment_name", "../x"),
        ("--method-name", "method_name", "../../y"),
    ],
)
def test_a_name_that_would_leave_the_output_dir_is_refused(flag, field, value, toy_scene, tmp_path):
    out = tmp_path / "deep" / "outputs"
    config = tiny_run_config(toy_scene, out, 2, **{field: value})
    line = _train_exits(config)
    assert line.startswith(f"naka-gs: {flag} {value}: the run folder would lie outside --output-dir {out} -- ")
    assert _tree(tmp_path) == {}  # nothing written anywhere


@pytest.mark.parametrize("kind", ["a folder", "a FIFO"])
def test_a_run_claim_that_is_not_a_file_is_named_and_left_alone(kind, toy_scene, tmp_path):
    config = tiny_run_config(toy_scene, tmp_path / "outputs", 2)
    run = config.get_base_dir()
    run.mkdir(parents=True)
    claim = run / RUN_CLAIM
    if kind == "a folder":
        claim.mkdir()
        (claim / "keep.txt").write_text("mine")
    else:
        os.mkfifo(claim)
    before = _tree(tmp_path)
    line = _train_exits(config)
    assert line.startswith(f"naka-gs: {claim} is {kind}, not a run claim"), line
    assert _tree(tmp_path) == before


@pytest.mark.slow
def test_a_path_too_long_for_the_system_is_one_line(toy_scene, tmp_path):
    """A ``--output-dir`` of about 4,000 characters: the run folder can be made, the files in it (the event writer's,
    the checkpoints) pass the system's limit of 4,096."""
    run_suffix = len("/scene/naka-gs/run")
    out = tmp_path
    while len(str(out)) + run_suffix < 4060:
        out = out / ("d" * min(200, 4060 - run_suffix - len(str(out)) - 1))
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "ns-train"), "naka-gs", "--data", str(toy_scene), "--output-dir",
            str(out), "--max-num-iterations", "2", "--vis", "tensorboard", "--timestamp", "run",
            "--pipeline.model.num-random", "500", "--pipeline.datamanager.enhance.correction", "none",
        ],
        capture_output=True, text=True, timeout=600, env=dict(os.environ, TORCHDYNAMO_DISABLE="1"),
    )  # fmt: skip
    lines = [line for line in proc.stderr.splitlines() + proc.stdout.splitlines() if line.startswith("naka-gs:")]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert len(lines) == 1 and "the run folder's path is" in lines[0], lines
    assert lines[0].endswith("-- choose a shorter --output-dir"), lines
    assert not any(p.is_file() for p in tmp_path.rglob("*"))  # refused before anything was written
