"""The accuracy-vs-time grid: a tiny smoke grid runs, records failures, resumes and reproduces."""

import copy
import json
from pathlib import Path

import pytest

from benchmarks.grid import Bench, BenchSpecError, load_grid, pareto, set_setting
from naka_gs_plugin.shipped import CONFIGS

GRIDS = Path(__file__).resolve().parents[2] / "benchmarks" / "configs"


def _grid(tmp_path: Path, scene: Path, families: str) -> Path:
    path = tmp_path / "grid.yaml"
    path.write_text(
        f"""name: tiny
seed: 0
scenes:
  toy: {{data: {scene}}}
milestones: [3, 6]
base:
  pipeline.model.num_random: 500
  pipeline.model.random_scale: 2.0
families:
{families}
"""
    )
    return path


FAMILIES = """  naka-gs: {}
  baseline-raw: {enhance: none}
  gsplat-on-cpu: {rasterizer: gsplat}
"""


def test_smoke_grid_runs_records_failure_resumes_and_reports(tmp_path, toy_scene):
    grid = _grid(tmp_path, toy_scene, FAMILIES)
    out = tmp_path / "out"
    results = Bench(grid, out=out).main()
    runs = results["runs"]
    assert set(runs) == {"toy/naka-gs", "toy/baseline-raw", "toy/gsplat-on-cpu"}
    for rid in ("toy/naka-gs", "toy/baseline-raw"):
        run = runs[rid]
        assert run["status"] == "ok", run.get("error")
        assert [e["step"] for e in run["evals"]] == [3, 6]
        assert all(
            e["psnr"] > 0 and 0 < e["lpips"] < 1.5 and e["gaussians"] > 0 and e["render_ms_per_image"] > 0
            for e in run["evals"]
        )
        assert run["evals"][0]["train_s"] < run["evals"][1]["train_s"]
        assert run["peak_rss_gb"] > 0.1 and run["stages"]["setup_s"] > 0
    # Naka is timed when it runs and is absent from the raw baseline.
    assert runs["toy/naka-gs"]["stages"]["enhance_s"] > 0
    assert runs["toy/baseline-raw"]["stages"]["enhance_s"] == 0
    # gsplat needs CUDA: that run fails with its reason recorded and the grid carried on.
    failed = runs["toy/gsplat-on-cpu"]
    assert failed["status"] == "failed" and "gsplat" in failed["error"] and "CUDA" in failed["error"]
    table = (out / "results.md").read_text()
    assert "| toy/naka-gs | ok | 6 |" in table and "| toy/gsplat-on-cpu | failed:" in table
    assert (out / "psnr_vs_seconds.png").stat().st_size > 1000 and (out / "psnr_vs_steps.png").stat().st_size > 1000

    # Resume: nothing is redone (the stored records come back unchanged, wall times included).
    again = Bench(grid, out=out).main()
    assert again["runs"] == runs

    # Same seed, fresh folder: the quality figures are reproduced exactly.
    repeat = Bench(grid, out=tmp_path / "repeat", only=("naka-gs",)).main()["runs"]
    assert list(repeat) == ["toy/naka-gs"]
    assert [e["psnr"] for e in repeat["toy/naka-gs"]["evals"]] == [e["psnr"] for e in runs["toy/naka-gs"]["evals"]]
    assert json.loads((out / "results.json").read_text())["runs"] == runs


def test_unknown_setting_is_rejected_naming_the_file(tmp_path, toy_scene):
    grid = _grid(tmp_path, toy_scene, "  typo: {pipeline.model.sh_degre: 1}\n")
    with pytest.raises(BenchSpecError, match=r"grid\.yaml: setting 'pipeline\.model\.sh_degre'.*no field 'sh_degre'"):
        load_grid(grid)


def test_a_family_starts_from_the_preset_it_names(tmp_path, toy_scene):
    """``method: naka-gs-fast`` runs the fast preset's config (its schedule and length), other settings on
    top; a name that is no preset is refused naming the file and the presets."""
    from benchmarks.grid import grid_runs, method_config
    from naka_gs_plugin.config import naka_gs_fast_method, naka_gs_method

    grid = _grid(tmp_path, toy_scene, "  fast: {method: naka-gs-fast, sh_degree: 1}\n")
    run = next(r for r in grid_runs(load_grid(grid), tmp_path) if r["family"] == "fast")
    config = method_config(run["settings"])
    fast, default = naka_gs_fast_method.config, naka_gs_method.config
    assert config.method_name == "naka-gs-fast" and run["settings"]["sh_degree"] == 1
    assert run["milestones"] == [3, 6, fast.max_num_iterations]  # the grid's, then the preset's own length
    assert (
        config.pipeline.model.stop_split_at == fast.pipeline.model.stop_split_at != default.pipeline.model.stop_split_at
    )
    assert config.optimizers["means"]["scheduler"].max_steps == fast.optimizers["means"]["scheduler"].max_steps
    assert method_config({}).method_name == "naka-gs"
    with pytest.raises(
        BenchSpecError, match=r"grid\.yaml: method 'naka-gs-slow' is not a naka-gs preset.*naka-gs-fast"
    ):
        load_grid(_grid(tmp_path, toy_scene, "  slow: {method: naka-gs-slow}\n"))


def test_settings_reach_into_the_optimizer_dict():
    """``optimizers.<group>.scheduler.max_steps`` sets that group's schedule; an unknown group is an error."""
    from naka_gs_plugin.config import naka_gs_method

    config = copy.deepcopy(naka_gs_method.config)
    set_setting(config, "optimizers.means.scheduler.max_steps", 1234)
    assert config.optimizers["means"]["scheduler"].max_steps == 1234
    assert naka_gs_method.config.optimizers["means"]["scheduler"].max_steps != 1234
    with pytest.raises(AttributeError, match=r"no key 'meens' in \[.*'means'"):
        set_setting(config, "optimizers.meens.scheduler.max_steps", 1)


def test_missing_grid_file_names_the_shipped_grids(tmp_path):
    with pytest.raises(BenchSpecError, match=r"no such grid file.*smoke\.yaml"):
        load_grid(tmp_path / "nope.yaml")


def test_pareto_front_keeps_only_undominated_points():
    points = [(1.0, 10.0), (2.0, 9.0), (3.0, 12.0), (4.0, 12.0), (5.0, 13.0)]
    assert sorted(pareto(points)) == [0, 2, 4]


def test_every_shipped_grid_loads():
    """Each benchmarks/configs/*.yaml names settings that exist (the LOM protocol's per-scene weights too)."""
    grids = sorted(g for g in GRIDS.glob("*.yaml") if g.name != "realx3d.yaml")  # benchmarks.realx3d's, not a grid
    assert any(g.name == "lom-holdout.yaml" for g in grids)
    for grid in grids:
        spec = load_grid(grid)
        assert spec.milestones and spec.families
    holdout = load_grid(Path("benchmarks/configs/lom-holdout.yaml"))
    for name, scene in holdout.scenes.items():
        assert scene["correction"] == f"outputs/correction-loo/{name}/best.pt" and scene["data"].endswith(f"lom/{name}")


def test_grid_paths_resolve_from_any_folder(tmp_path, monkeypatch):
    """``benchmarks/configs/...`` works from any folder (this clone's file), and a user's own file at that path wins;
    the simulator specs a grid names (``configs/scenes/...``) are the package's."""
    from naka_gs_plugin.shipped import config_file

    monkeypatch.chdir(tmp_path)
    assert load_grid(Path("benchmarks/configs/smoke.yaml")).path == GRIDS / "smoke.yaml"
    own = tmp_path / "benchmarks" / "configs" / "smoke.yaml"
    own.parent.mkdir(parents=True)
    own.write_text((GRIDS / "smoke.yaml").read_text().replace("name: smoke", "name: mine"))
    assert load_grid(Path("benchmarks/configs/smoke.yaml")).name == "mine"
    assert config_file(Path("configs/scenes/dark-noisy.yaml")) == CONFIGS / "scenes" / "dark-noisy.yaml"


def test_the_realx3d_benchmark_file_loads_and_a_bad_one_is_one_line(tmp_path):
    """benchmarks/configs/realx3d.yaml names the calibration pairs and the eight scenes; a file without them is refused."""
    from benchmarks.realx3d import RealX3DSpecError, load_spec

    spec = load_spec(GRIDS / "realx3d.yaml")
    assert spec["calibrate"].endswith("realx3d/BlueHawaii") and len(spec["scenes"]) == 8
    bad = tmp_path / "bad.yaml"
    bad.write_text("scenes: {}\n")
    with pytest.raises(RealX3DSpecError, match="needs 'calibrate: PAIRS'") as err:
        load_spec(bad)
    assert "\n" not in str(err.value)
