"""python -m benchmarks.wall_ab: each side from its own worktree, fresh caches per run, sides alternated, the
figures read from what ns-train and ns-eval wrote (stand-ins for both here: a real run takes minutes)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import benchmarks.wall_ab as bench

FAKE_TRAIN = """\
import json, os, sys
from pathlib import Path
import naka_gs_plugin.config as config
arg = dict(zip(sys.argv[1::2], sys.argv[2::2]))
scene = Path(sys.argv[sys.argv.index("--data") + 1])
caches = [Path(os.environ[k]) for k in ("NAKA_GS_CACHE", "NUMBA_CACHE_DIR")]
with open(os.environ["WALL_AB_ORDER"], "a") as fh:
    fh.write(json.dumps([scene.name, config.SIDE, [str(c) for c in caches], [any(c.iterdir()) for c in caches]]) + "\\n")
for c in caches:
    (c / "used").write_text("x")
ms = config.STEP_MS
print("[naka-gs] cpu-fast rasterizer: torch.float32 kernels compiled (and cached on disk)  x.py:1\\n           in 12.5 s")
for step in range(0, 7001, 10):
    t = f"{ms * 4:.3f} ms" if step > 6500 else (f"{ms * 2:.3f} ms" if step > 3250 else f"{ms:.3f} ms")
    print(f"{step} ({100 * step / 7000:.2f}%)       {t}            1 m, 2 s")
run = Path(sys.argv[sys.argv.index("--output-dir") + 1]) / scene.name / sys.argv[1] / "run"
run.mkdir(parents=True)
(run / "config.yml").write_text(config.SIDE)
"""

FAKE_EVAL = """\
import json, sys
from pathlib import Path
config = Path(sys.argv[sys.argv.index("--load-config") + 1])
side = config.read_text()
out = Path(sys.argv[sys.argv.index("--output-path") + 1])
out.write_text(json.dumps({"results": {"psnr": 20.0 if side == "old" else 21.0, "ssim": 0.5, "lpips": 0.25}}))
"""


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout


@pytest.fixture
def fake_project(tmp_path, monkeypatch):
    """A git repository with an old and a new commit of a stand-in ``naka_gs_plugin.config`` (the old one
    without ``naka_gs_fast_method``), stand-in ns-train / ns-eval, and two scenes."""
    repo = tmp_path / "repo"
    package = repo / "naka_gs_plugin"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    _git(repo, "init", "-q")
    _git(repo, "config", "user.email", "t@t")
    _git(repo, "config", "user.name", "t")
    (package / "config.py").write_text("SIDE = 'old'\nSTEP_MS = 20.0\nnaka_gs_method = 'naka-gs'\n")
    _git(repo, "add", ".")
    _git(repo, "commit", "-qm", "old")
    old = _git(repo, "rev-parse", "HEAD").strip()
    (package / "config.py").write_text(
        "SIDE = 'new'\nSTEP_MS = 10.0\nnaka_gs_method = 'naka-gs'\nnaka_gs_fast_method = 'naka-gs-fast'\n"
    )
    _git(repo, "commit", "-qam", "new")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, source in (("ns-train", FAKE_TRAIN), ("ns-eval", FAKE_EVAL)):
        (bin_dir / name).write_text(f"#!{sys.executable}\n" + textwrap.dedent(source))
        (bin_dir / name).chmod(0o755)
    scenes = []
    for name in ("a", "b"):
        scene = tmp_path / "scenes" / name
        scene.mkdir(parents=True)
        (scene / "transforms_train.json").write_text("{}")
        scenes.append(scene)
    order = tmp_path / "order.jsonl"
    monkeypatch.setattr(bench, "REPO", repo)
    monkeypatch.setattr(bench, "NS_BIN", bin_dir)
    monkeypatch.setenv("WALL_AB_ORDER", str(order))
    return repo, old, scenes, order


@pytest.mark.skipif(not Path("/usr/bin/time").exists(), reason="needs GNU time (/usr/bin/time)")
def test_each_side_runs_from_its_revision_with_fresh_caches_in_alternating_order(fake_project, tmp_path, capsys):
    repo, old, scenes, order = fake_project
    work = tmp_path / "work"
    rows = bench.entrypoint(["--old", old, "--scenes", *map(str, scenes), "--work", str(work)])
    printed = capsys.readouterr().out
    assert "lacks naka_gs_plugin.config:naka_gs_fast_method" in printed  # the old tree, bound in its worktree
    runs = [json.loads(line) for line in order.read_text().splitlines()]
    assert [(scene, side) for scene, side, _, _ in runs] == [("a", "old"), ("a", "new"), ("b", "new"), ("b", "old")]
    assert all(not any(used) for _, _, _, used in runs)  # every run found its caches empty
    assert len({c for _, _, caches, _ in runs for c in caches}) == 8  # and they were its own
    assert [name for name, _, _ in rows] == ["a", "b"]
    for _, old_row, new_row in rows:
        assert old_row["phases"] == [20.0, 40.0, 80.0] and new_row["phases"] == [10.0, 20.0, 40.0]
        assert old_row["compile"] == new_row["compile"] == 12.5
        assert old_row["scores"] == (20.0, 0.5, 0.25) and new_row["scores"] == (21.0, 0.5, 0.25)
        assert old_row["wall"] > 0 and new_row["wall"] > 0
    assert "| **mean** |" in printed
    assert len(_git(repo, "worktree", "list").splitlines()) == 1  # the bench's worktrees removed
    assert (repo / "naka_gs_plugin" / "config.py").read_text().count("naka_gs_fast_method") == 1  # repo untouched


def test_step_times_read_nerfstudios_progress_lines():
    log = (
        "0 (0.00%)           54 s, 104.968 ms     4 d\n3330 (47.57%)       41.542 ms   2 m\n6990 (99.9%)  1.250 s  x\n"
    )
    assert bench.step_times(log) == {0: 54104.968, 3330: 41.542, 6990: 1250.0}
    assert bench.phase_medians({500: 1.0, 3250: 3.0, 3260: 5.0, 7000: 9.0}, (500, 3250, 6500, 7000)) == [2.0, 5.0, 9.0]


def test_a_folder_that_is_not_a_scene_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="--scenes: no transforms_train.json in"):
        bench.entrypoint(["--old", "HEAD", "--scenes", str(tmp_path)])


def test_an_unknown_revision_and_a_used_work_folder_are_refused(fake_project, tmp_path):
    _, old, scenes, _ = fake_project
    with pytest.raises(SystemExit, match="--old nosuchrev: not a commit of"):
        bench.entrypoint(["--old", "nosuchrev", "--scenes", str(scenes[0])])
    (tmp_path / "work" / "old").mkdir(parents=True)
    with pytest.raises(SystemExit, match="holds an earlier run"):
        bench.entrypoint(["--old", old, "--scenes", str(scenes[0]), "--work", str(tmp_path / "work")])


@pytest.mark.skipif(not Path("/usr/bin/time").exists(), reason="needs GNU time (/usr/bin/time)")
def test_a_work_folder_deleted_after_an_interrupted_run_can_be_used_again(fake_project, tmp_path):
    """An interrupted run leaves its worktrees registered; with its work folder deleted, the same folder works."""
    repo, old, scenes, _ = fake_project
    work = tmp_path / "work"
    _git(repo, "worktree", "add", "--detach", str(work / "tree-old"), old)  # as an interrupted run left it
    shutil.rmtree(work)
    rows = bench.entrypoint(["--old", old, "--scenes", str(scenes[0]), "--work", str(work)])
    assert [name for name, _, _ in rows] == ["a"]
