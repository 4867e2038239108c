"""A scene converted to nerfstudio-data and to colmap trains through ``ns-train naka-gs <layout>`` and scores as the
lowlight-data run does on the same normal-light test views (``benchmarks.layouts``, tiny); ``ns-eval`` on such a run
says in one line that there is no normal-light truth, and writes no metrics."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.layouts import Args
from naka_gs_plugin.sim.generate import generate
from naka_gs_plugin.sim.spec import load_spec
from tests.helpers import TINY_VIEWS, write_spec

TINY = (
    "--max-num-iterations 60 --pipeline.model.num-random 2000 --machine.seed 0 "
    "--pipeline.datamanager.enhance.correction none --pipeline.datamanager.enhance.use-cache False"
)


@pytest.mark.slow  # three ns-train runs and an ns-eval in subprocesses
def test_three_layouts_train_and_score_alike_and_ns_eval_refuses_dark_truth(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHDYNAMO_DISABLE", "1")
    views = {**TINY_VIEWS, "n_train": 8, "n_test": 2, "width": 64, "height": 48}
    points = {"n_points": 500, "n_clusters": 1, "cluster_size": 50}
    spec = write_spec(tmp_path, [{"exposure": {"factor": 0.05}}], source={"procedural": {**views, "points": points}})
    scene = generate(load_spec(spec), tmp_path / "scene", seed=0)
    before = sorted(str(p) for p in scene.rglob("*"))

    results = Args(scene=scene, out=tmp_path / "out", method="naka-gs", train_options=TINY).main()

    assert sorted(str(p) for p in scene.rglob("*")) == before  # nothing written into the scene
    reference = results["lowlight-data"]
    assert reference["psnr"] > 12.0, results
    for layout in ("nerfstudio-data", "colmap"):
        assert abs(results[layout]["psnr"] - reference["psnr"]) < 0.5, results
        assert abs(results[layout]["ssim"] - reference["ssim"]) < 0.03, results

    run = tmp_path / "out" / "runs" / "nerfstudio-data" / "naka-gs" / "run"
    out = tmp_path / "eval.json"
    ns_eval = [str(Path(sys.executable).parent / "ns-eval"), "--load-config", str(run / "config.yml")]
    res = subprocess.run(
        [*ns_eval, "--output-path", str(out)], capture_output=True, text=True, env=dict(os.environ), timeout=300
    )
    assert res.returncode == 1 and not out.exists(), res.stderr[-3000:]
    lines = [line for line in res.stderr.splitlines() if line.startswith("naka-gs:")]
    assert len(lines) == 1 and "no normal-light truth (nerfstudio-data layout" in lines[0], res.stderr[-3000:]
