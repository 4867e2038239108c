"""``python -m benchmarks.grid``: what accuracy costs in time, as a resumable grid of training runs.

A grid file (``benchmarks/configs/*.yaml``) names scenes with ground truth (any ``lowlight-data`` scene
with test images, e.g. LOM, or a simulator spec that is generated on the fly), a list of evaluation
milestones in training steps, a ``base`` of settings shared by every run and ``families``: named
settings that differ from the base (correction off, random init, another rasterizer, ...). Every
(scene, family) pair is one run: one ``naka-gs`` training to the last milestone, evaluated on the
test views at every milestone (the clock is paused while it evaluates). Each run executes in its
own process so that its peak memory is its own and a crash cannot take the grid down.

Settings are dotted paths into the nerfstudio ``TrainerConfig`` (``pipeline.model.sh_degree``),
or one of the short aliases in :data:`ALIASES`. A path that does not exist is an error, never
ignored. ``method: naka-gs-fast`` starts a family from another registered preset, trained for that
preset's own length (evaluated at the grid's milestones before it and at its end).

Per run the result records wall time of each stage (enhance, correction, points/PPM, training up
to each milestone, rendering and evaluation), PSNR / SSIM / LPIPS,
Gaussian count and peak resident memory. Outputs in ``--out``: ``results.json`` (all runs),
``results.md`` (a table), ``psnr_vs_seconds.png`` (one curve per family, Pareto front marked) and
``psnr_vs_steps.png``. Re-running resumes: finished runs (``ok`` or ``failed``) are not redone.

Run from the repository root: ``python -m benchmarks.grid --help``.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import random
import resource
import shutil
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import tyro
import yaml
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.progress import StageProgress
from naka_gs_plugin.shipped import config_file

REPO = Path(__file__).resolve().parents[1]
"""The clone this benchmark runs from; grid paths ``benchmarks/configs/...`` resolve against it."""

ALIASES: Dict[str, str] = {
    "steps": "max_num_iterations",
    "downscale": "pipeline.datamanager.dataparser.downscale_factor",
    "enhance": "pipeline.datamanager.enhance.method",
    "correction": "pipeline.datamanager.enhance.correction",
    "rasterizer": "pipeline.model.rasterizer",
    "sh_degree": "pipeline.model.sh_degree",
    "points": "pipeline.init.points",
    "ppm": "pipeline.init.ppm",
    "voxel_size": "pipeline.init.voxel_size",
}
"""Short names for the settings a grid usually varies."""


class BenchSpecError(ValueError):
    """A grid file that cannot be run; the message names the file and the fix."""


class BenchRunsFailed(RuntimeError):
    """Every run of the grid failed (results and reports are written); one line."""


@dataclass
class GridSpec:
    """A parsed ``benchmarks/configs/*.yaml``."""

    name: str
    path: Path
    scenes: Dict[str, Dict[str, Any]]
    """name -> {data: scene dir} or {sim: spec yaml}, optionally with per-scene settings."""
    milestones: List[int]
    """Training steps at which the test views are evaluated; the last one is the run length."""
    base: Dict[str, Any]
    families: Dict[str, Dict[str, Any]]
    seed: int = 0


def load_grid(path: Path) -> GridSpec:
    """Parse and check a grid file (``benchmarks/configs/...`` is found from any directory)."""
    path = Path(path)
    if not path.exists() and not path.is_absolute() and (REPO / path).exists():
        path = REPO / path
    if not path.is_file():
        shipped = sorted(f"benchmarks/configs/{p.name}" for p in (REPO / "benchmarks" / "configs").glob("*.yaml"))
        raise BenchSpecError(f"{path}: no such grid file -- pass one of {shipped}")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise BenchSpecError(
            f"{path}: malformed YAML ({problem}{where}) -- fix the syntax; see benchmarks/configs/smoke.yaml"
        ) from None
    if not isinstance(raw, dict):
        raise BenchSpecError(f"{path}: not a mapping of name, scenes, milestones, base, families -- see smoke.yaml")
    unknown = set(raw) - {"name", "scenes", "milestones", "base", "families", "seed"}
    if unknown:
        raise BenchSpecError(
            f"{path}: unknown keys {sorted(unknown)} -- allowed: name, scenes, milestones, base, families, seed"
        )
    for key in ("scenes", "milestones", "families"):
        if not raw.get(key):
            raise BenchSpecError(
                f"{path}: '{key}' is missing or empty -- see benchmarks/configs/smoke.yaml for the format"
            )
    for key in ("scenes", "families"):
        if not isinstance(raw[key], dict) or not isinstance(raw.get("base") or {}, dict):
            raise BenchSpecError(f"{path}: '{key}' and 'base' are mappings (name: settings) -- see smoke.yaml")
    try:
        milestones = sorted(int(s) for s in raw["milestones"])
    except (TypeError, ValueError):
        raise BenchSpecError(f"{path}: milestones must be a list of step counts, got {raw['milestones']!r}") from None
    if milestones[0] < 1:
        raise BenchSpecError(f"{path}: milestones must be positive step counts, got {milestones}")
    scenes = {}
    for name, scene in raw["scenes"].items():
        if not isinstance(scene, dict) or len({"data", "sim"} & set(scene)) != 1:
            raise BenchSpecError(
                f"{path}: scene '{name}' needs exactly one of 'data: <scene dir>' or 'sim: <spec yaml>'"
            )
        scenes[name] = dict(scene)
    if not all(isinstance(f or {}, dict) for f in raw["families"].values()):
        raise BenchSpecError(f"{path}: every family is a mapping of settings ({{}} for none) -- see smoke.yaml")
    families = {name: dict(f or {}) for name, f in raw["families"].items()}
    spec = GridSpec(
        name=str(raw.get("name", path.stem)),
        path=path,
        scenes=scenes,
        milestones=milestones,
        base=dict(raw.get("base") or {}),
        families=families,
        seed=int(raw.get("seed", 0)),
    )
    # Fail before the first run on a setting that does not exist.
    for settings in [
        spec.base,
        *spec.families.values(),
        *({k: v for k, v in s.items() if k not in ("data", "sim")} for s in scenes.values()),
    ]:
        try:
            probe = method_config(settings)
        except KeyError as err:
            raise BenchSpecError(f"{path}: {err.args[0]}") from None
        for key, value in settings.items():
            try:
                if key != "method":
                    set_setting(probe, key, value)
            except (AttributeError, TypeError) as err:
                raise BenchSpecError(f"{path}: setting '{key}': {err}") from None
    return spec


def _resolve(path: str, relative_to: Path) -> Path:
    p = Path(os.path.expanduser(path))
    if p.is_absolute():
        return p
    for root in (Path.cwd(), relative_to.parent):
        if (root / p).exists():
            return (root / p).resolve()
    return config_file(p).resolve()


def method_config(settings: Dict[str, Any]) -> Any:
    """A fresh copy of the config of the preset ``settings["method"]`` names (default ``naka-gs``)."""
    from naka_gs_plugin.config import METHODS

    name = settings.get("method", "naka-gs")
    if name not in METHODS:
        raise KeyError(f"method '{name}' is not a naka-gs preset -- use one of {sorted(METHODS)}")
    return copy.deepcopy(METHODS[name].config)


def set_setting(config: Any, key: str, value: Any) -> None:
    """Set a dotted path (or alias) on a nested dataclass config; unknown paths raise AttributeError.

    A dict on the way is entered by key, as ``optimizers.means.scheduler.max_steps``."""
    dotted = ALIASES.get(key, key)
    *parents, leaf = dotted.split(".")
    target = config
    for part in parents:
        if isinstance(target, dict):
            if part not in target:
                raise AttributeError(f"'{dotted}' does not exist (no key '{part}' in {sorted(target)})")
            target = target[part]
            continue
        if not hasattr(target, part):
            raise AttributeError(f"'{dotted}' does not exist ({type(target).__name__} has no '{part}')")
        target = getattr(target, part)
    if not dataclasses.is_dataclass(target) or leaf not in {f.name for f in dataclasses.fields(target)}:
        raise AttributeError(f"'{dotted}' does not exist ({type(target).__name__} has no field '{leaf}')")
    current = getattr(target, leaf)
    if isinstance(current, Path) and isinstance(value, str):
        value = Path(value)
    setattr(target, leaf, value)


# ---------------------------------------------------------------------------------------- one run
def run_one(run: Dict[str, Any], out: Path) -> Dict[str, Any]:
    """Train and evaluate one grid cell in this process; returns the result record."""
    import torch
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    seed = int(run["seed"])
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)

    config = method_config(run["settings"])
    config.data = config.pipeline.datamanager.data = Path(run["data"])
    config.output_dir = out / "runs"
    config.experiment_name = run["scene"]
    config.timestamp = run["family"]
    config.machine.seed = seed
    config.vis = "tensorboard"
    config.viewer.quit_on_train_completion = True
    last = int(run["milestones"][-1])
    config.max_num_iterations = last
    config.steps_per_save = last
    # nerfstudio's periodic evaluations would land inside the timed training; milestones replace them.
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = last + 1
    for key, value in run["settings"].items():
        if key != "method":
            set_setting(config, key, value)
    config.max_num_iterations = last
    config.save_config()

    stages: Dict[str, float] = {}
    t0 = time.perf_counter()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="val")  # as ns-train: the point source / PPM seeding runs in this mode only
    stages["setup_s"] = time.perf_counter() - t0
    pipeline = trainer.pipeline
    t = time.perf_counter()
    _ = pipeline.datamanager.cached_train  # nerfstudio loads (and we enhance) the training images lazily
    stages["setup_s"] += time.perf_counter() - t
    # The scores are on the test split (the val split can be a single view, as in LOM), loaded and
    # undistorted by nerfstudio's own datamanager exactly as ns-eval does.
    test_views = config.pipeline.datamanager.setup(
        device=pipeline.device, test_mode="test"
    ).fixed_indices_eval_dataloader
    enhancer_run = dict(getattr(pipeline.datamanager, "enhancer").last_run)
    stages["enhance_s"] = float(enhancer_run.get("naka_seconds", enhancer_run.get("seconds", 0.0)))
    stages["correction_s"] = float(enhancer_run.get("correction_seconds", 0.0))
    seeding = getattr(pipeline, "seeding", None)
    points = seeding.summary if seeding is not None else {}
    stages["points_s"] = float(sum(points.get("timings_s", {}).values())) + float(
        points.get("triangulation", {}).get("total_seconds", 0.0)
    )

    evals: List[Dict[str, Any]] = []
    clock = {"train": 0.0, "resumed": 0.0}

    def evaluate(step: int) -> None:
        clock["train"] += time.perf_counter() - clock["resumed"]
        t = time.perf_counter()
        pipeline.eval()
        render_s, scores = 0.0, []
        with torch.no_grad():
            for camera, batch in test_views:
                r = time.perf_counter()
                outputs = pipeline.model.get_outputs_for_camera(camera)
                render_s += time.perf_counter() - r
                scores.append(pipeline.model.get_image_metrics_and_images(outputs, batch)[0])
        pipeline.train()
        eval_s = time.perf_counter() - t
        record = {
            "step": step + 1,
            "train_s": round(clock["train"], 3),
            "eval_s": round(eval_s, 3),
            "psnr": float(np.mean([m["psnr"] for m in scores])),
            "ssim": float(np.mean([m["ssim"] for m in scores])),
            "lpips": float(np.mean([m["lpips"] for m in scores])),
            "gaussians": int(pipeline.model.num_points),
            "render_ms_per_image": round(1000.0 * render_s / len(test_views), 2),
        }
        evals.append(record)
        CONSOLE.print(
            f"[naka-gs bench] {run['scene']}/{run['family']} step {record['step']}: PSNR {record['psnr']:.2f} dB, "
            f"SSIM {record['ssim']:.3f}, LPIPS {record['lpips']:.3f}, "
            f"{record['gaussians']} Gaussians, {record['train_s']:.1f} s training",
            markup=False,
        )
        clock["resumed"] = time.perf_counter()

    trainer.callbacks.append(
        TrainingCallback(
            [TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
            evaluate,
            iters=tuple(int(m) - 1 for m in run["milestones"]),
        )
    )
    clock["resumed"] = time.perf_counter()
    trainer.train()
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "stages": {k: round(v, 3) for k, v in stages.items()},
        "evals": evals,
        "peak_rss_gb": round(rss_kb / 1024**2, 3),
        "points": {"source": points.get("source", "random"), "count": points.get("final_count")},
        "config": str(config.get_base_dir() / "config.yml"),
    }


# ---------------------------------------------------------------------------------------- the grid
def grid_runs(spec: GridSpec, out: Path) -> List[Dict[str, Any]]:
    runs = []
    for scene_name, scene in spec.scenes.items():
        scene_settings = {k: v for k, v in scene.items() if k not in ("data", "sim")}
        for family, settings in spec.families.items():
            merged = {**spec.base, **scene_settings, **settings}
            runs.append(
                {
                    "id": f"{scene_name}/{family}",
                    "scene": scene_name,
                    "family": family,
                    "scene_source": {k: scene[k] for k in ("data", "sim") if k in scene},
                    "settings": merged,
                    "milestones": _milestones(spec.milestones, merged),
                    "seed": spec.seed,
                }
            )
    return runs


def _milestones(milestones: List[int], settings: Dict[str, Any]) -> List[int]:
    """The grid's milestones; a family that names a preset runs that preset's own length, so it is evaluated
    at the grid's milestones before it and at its last step."""
    if "method" not in settings:
        return milestones
    length = method_config(settings).max_num_iterations
    return [m for m in milestones if m < length] + [length]


def _scene_dir(source: Dict[str, str], spec: GridSpec, out: Path) -> Path:
    if "data" in source:
        path = _resolve(source["data"], spec.path)
        if not (path / "transforms_test.json").exists():
            raise BenchSpecError(
                f"{spec.path}: scene {path} has no transforms_test.json -- the grid needs scenes with test views"
            )
        return path
    from naka_gs_plugin.sim.generate import generate
    from naka_gs_plugin.sim.spec import load_spec

    sim_spec = load_spec(_resolve(source["sim"], spec.path))
    scene_dir = out / "scenes" / sim_spec.name
    if not (scene_dir / "sim_manifest.json").exists():
        generate(sim_spec, scene_dir, seed=spec.seed)
    return scene_dir


def execute(run: Dict[str, Any], spec: GridSpec, out: Path, timeout_s: int) -> Dict[str, Any]:
    """Run one grid run in its own process (see :func:`run_one`); a failure is recorded, never raised."""
    record = dict(run)
    start = time.perf_counter()
    try:
        run = dict(run, data=str(_scene_dir(run["scene_source"], spec, out)))
        run_file = out / "logs" / run["scene"] / run["family"] / "run.json"
        run_file.parent.mkdir(parents=True, exist_ok=True)
        run_file.write_text(json.dumps(run))
        result_file = run_file.with_name("result.json")
        result_file.unlink(missing_ok=True)
        shutil.rmtree(run_file.parent / "cache", ignore_errors=True)  # cold: every stage is really timed
        log = run_file.with_name("log.txt")
        with open(log, "w") as fh:
            proc = subprocess.run(
                [sys.executable, "-m", "benchmarks.grid", "--run", str(run_file), "--out", str(out)],
                stdout=fh,
                stderr=subprocess.STDOUT,
                timeout=timeout_s,
                # A private cache per run: enhancement, correction and PPM are computed, hence timed.
                env={
                    **os.environ,
                    "TORCHDYNAMO_DISABLE": os.environ.get("TORCHDYNAMO_DISABLE", "1"),
                    "NAKA_GS_CACHE": str(run_file.parent / "cache"),
                    # benchmarks/ is not installed: the child finds it in this clone.
                    "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
                },
            )
        outcome = json.loads(result_file.read_text()) if result_file.exists() else None
        if proc.returncode != 0 or outcome is None or "error" in outcome:
            error = (outcome or {}).get("error") or _last_line(log) or f"exit status {proc.returncode}"
            raise RuntimeError(error)
        record.update(outcome, status="ok")
    except subprocess.TimeoutExpired:
        record.update(status="failed", error=f"timed out after {timeout_s} s")
    except Exception as err:  # a failed run is recorded and the grid carries on
        record.update(status="failed", error=f"{type(err).__name__}: {err}")
    record["wall_s"] = round(time.perf_counter() - start, 1)
    if record["status"] == "failed":
        CONSOLE.print(f"[naka-gs bench] {record['id']} failed: {record['error']}", markup=False)
    return record


def _last_line(log: Path) -> str:
    lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def machine_description() -> str:
    import platform

    import psutil
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{platform.processor() or platform.machine()}, {psutil.cpu_count()} cores, {psutil.virtual_memory().total / 1024**3:.0f} GB RAM, {gpu}"


# ---------------------------------------------------------------------------------------- report
def _points(run: Dict[str, Any]) -> List[Tuple[float, int, float]]:
    """(seconds to reach the milestone incl. preprocessing, step, PSNR) per evaluated milestone."""
    pre = run["stages"]["setup_s"]
    return [(pre + e["train_s"], e["step"], e["psnr"]) for e in run["evals"]]


def pareto(points: Sequence[Tuple[float, float]]) -> List[int]:
    """Indices of the (seconds, PSNR) points no other point beats on both (less time, more PSNR)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -np.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def markdown_table(results: Dict[str, Any]) -> str:
    rows = [
        f"Grid `{results['grid']}` on {results.get('machine', '')}. Times in seconds; setup = data loading + "
        "enhancement + correction + points/PPM + model creation; train = training up to the milestone "
        "(evaluation excluded).",
        "",
        "| run | status | step | PSNR | SSIM | LPIPS | Gaussians | seed points | enhance | correction | points | setup | train | render ms/img | eval | peak RSS GB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for rid, run in results["runs"].items():
        if run["status"] != "ok":
            rows.append(f"| {rid} | failed: {run.get('error', '')[:120]} |" + " |" * 14)
            continue
        s = run["stages"]
        pts = run.get("points") or {}
        kind = str(pts.get("source", "?")).split(" ")[0]  # "PLY /path/points.ply" -> "PLY"
        seed = kind + (f" ({pts['count']})" if pts.get("count") else "")
        for e in run["evals"]:
            lp = f"{e['lpips']:.3f}" if "lpips" in e else "n/a"  # records written before LPIPS was offline
            rows.append(
                f"| {rid} | ok | {e['step']} | {e['psnr']:.2f} | {e['ssim']:.3f} | {lp} | {e['gaussians']} | {seed} | "
                f"{s.get('enhance_s', 0):.2f} | {s.get('correction_s', 0):.2f} | {s.get('points_s', 0):.2f} | "
                f"{s['setup_s']:.1f} | {e['train_s']:.1f} | {e.get('render_ms_per_image') or 'n/a'} | {e['eval_s']:.1f} | "
                f"{run['peak_rss_gb']:.2f} |"
            )
    return "\n".join(rows) + "\n"


def plot(results: Dict[str, Any], out: Path) -> None:
    """psnr_vs_seconds.png (Pareto front per scene marked) and psnr_vs_steps.png, one panel per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ok = [r for r in results["runs"].values() if r["status"] == "ok" and r["evals"]]
    scenes = sorted({r["scene"] for r in ok})
    if not scenes:
        return
    for kind in ("seconds", "steps"):
        fig, axes = plt.subplots(1, len(scenes), figsize=(5.5 * len(scenes), 4.2), squeeze=False)
        for ax, scene in zip(axes[0], scenes):
            allpts = []
            for r in sorted((r for r in ok if r["scene"] == scene), key=lambda r: r["family"]):
                pts = _points(r)
                xs = [p[0] if kind == "seconds" else p[1] for p in pts]
                ax.plot(xs, [p[2] for p in pts], marker="o", ms=3, label=r["family"])
                allpts += [(p[0], p[2]) for p in pts]
            if kind == "seconds" and allpts:
                front = sorted(allpts[i] for i in pareto(allpts))
                ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="k", lw=1, ls="--")
                ax.scatter(
                    [p[0] for p in front],
                    [p[1] for p in front],
                    s=60,
                    facecolors="none",
                    edgecolors="k",
                    label="Pareto front",
                )
            ax.set_title(scene)
            ax.set_xlabel("seconds (setup + training)" if kind == "seconds" else "training steps")
            ax.set_ylabel("test PSNR (dB)")
            if kind == "seconds":
                ax.set_xscale("log")
                # Plain numbers at 1-2-5 steps; matplotlib's own minor labels overlap on a log axis that
                # spans less than a decade or two.
                ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
                ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
                ax.xaxis.set_minor_formatter(NullFormatter())
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.suptitle(f"naka-gs bench '{results['grid']}' — {results.get('machine', '')}", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / f"psnr_vs_{kind}.png", dpi=110)
        plt.close(fig)


def _child(run_file: Path, out: Path) -> None:
    run = json.loads(run_file.read_text())
    result_file = run_file.with_name("result.json")
    try:
        result = run_one(run, out)
    except Exception as err:
        traceback.print_exc()
        result = {"error": f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"}
    result_file.write_text(json.dumps(result, indent=1))


@dataclass
class Bench:
    """Run (or resume) an accuracy-vs-time grid and write its table and plots."""

    grid: tyro.conf.Positional[Path]
    """Grid file, e.g. benchmarks/configs/cpu.yaml."""
    out: Optional[Path] = None
    """Output folder (default outputs/bench/<grid name>)."""
    only: Tuple[str, ...] = ()
    """Run only these run ids (scene/family) or families."""
    retry_failed: bool = False
    """Redo runs recorded as failed (finished ones are never redone)."""
    report_only: bool = False
    """Only rebuild results.md and the plots from results.json."""
    timeout_s: int = 4 * 3600
    """Per-run limit; a run past it is recorded as failed."""

    def main(self) -> Dict[str, Any]:
        spec = load_grid(self.grid)
        out = self.out or Path("outputs/bench") / spec.name
        out.mkdir(parents=True, exist_ok=True)
        results_path = out / "results.json"
        results: Dict[str, Any] = json.loads(results_path.read_text()) if results_path.exists() else {}
        results.setdefault("grid", spec.name)
        results.setdefault("runs", {})
        results["machine"] = machine_description()
        selected = list(results["runs"])
        if not self.report_only:
            runs = [
                r for r in grid_runs(spec, out) if not self.only or r["id"] in self.only or r["family"] in self.only
            ]
            selected = [r["id"] for r in runs]
            todo = []
            for r in runs:
                done = results["runs"].get(r["id"])
                if (
                    done is None
                    or (self.retry_failed and done["status"] == "failed")
                    or done.get("settings") != r["settings"]
                    or done.get("milestones") != r["milestones"]
                ):
                    todo.append(r)
            CONSOLE.print(
                f"[naka-gs bench] {spec.name}: {len(runs)} runs, {len(runs) - len(todo)} already done", markup=False
            )
            with StageProgress() as progress:
                task = progress.add_task("grid", total=len(todo))
                for r in todo:
                    progress.update(task, description=f"{r['id']}")
                    results["runs"][r["id"]] = execute(r, spec, out, self.timeout_s)
                    results_path.write_text(json.dumps(results, indent=1))  # checkpoint after every run
                    progress.advance(task)
        results_path.write_text(json.dumps(results, indent=1))
        (out / "results.md").write_text(markdown_table(results))
        plot(results, out)
        CONSOLE.print(
            f"[naka-gs bench] wrote {results_path}, results.md, psnr_vs_seconds.png, psnr_vs_steps.png", markup=False
        )
        failed = [rid for rid in selected if results["runs"][rid]["status"] == "failed"]
        if failed:
            first = f"{failed[0]}: {results['runs'][failed[0]].get('error', '')[:200]}"
            if len(failed) == len(selected):
                raise BenchRunsFailed(
                    f"all {len(failed)} runs failed (first {first}) -- see {out}/results.md and each run's "
                    "logs/<scene>/<family>/log.txt"
                )
            CONSOLE.print(
                f"[naka-gs bench] warning: {len(failed)} of {len(selected)} runs failed ({', '.join(failed)}); "
                "results.md lists their errors",
                markup=False,
                soft_wrap=True,
            )
        return results


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.grid``; a bad grid prints one line and exits with status 2, a grid whose
    every run failed with status 1."""
    try:
        tyro.cli(Bench, args=args).main()
    except BenchSpecError as err:
        CONSOLE.print(f"[naka-gs bench] error: {err}", markup=False, soft_wrap=True)
        raise SystemExit(2) from None
    except BenchRunsFailed as err:
        CONSOLE.print(f"[naka-gs bench] error: {err}", markup=False, soft_wrap=True)
        raise SystemExit(1) from None


if __name__ == "__main__":
    if sys.argv[1:2] == ["--run"]:  # internal: ``--run RUN_FILE --out OUT``, one run in this process (see execute)
        _child(Path(sys.argv[2]), Path(sys.argv[4]))
    else:
        entrypoint()
