"""The user's command, old tree against new, back to back: wall, peak memory, step times and scores per scene.

For each scene, ``ns-train METHOD --data SCENE --vis tensorboard`` runs once from each of two git revisions
(each checked out in a worktree of its own under the work folder and put first on ``PYTHONPATH``, so the
installed environment is shared), then ``ns-eval`` scores the run. Every run starts from an empty enhancement
cache and an empty numba cache (``NAKA_GS_CACHE``, ``NUMBA_CACHE_DIR``), as on a fresh install: the
enhancement is computed and the kernels are compiled in both columns. The two sides alternate which goes
first from one scene to the next (old-new, new-old, ...), since this VM's speed drifts within a session.
Printed: the CPU, then per scene both walls (``/usr/bin/time``), their ratio, peak RSS, the kernel compile
seconds and the median ms per step in each phase of the resolution schedule (``--phases``), and ``ns-eval``'s
PSNR / SSIM / LPIPS; last the mean ratio over the scenes. This is issue 34's "wall against issue time"
(docs/cpu.md). Run from the repository root on an idle machine, one heavy process at a time:

    python -m benchmarks.wall_ab --old 023ceac [--new HEAD] [--scenes ../shared/data/lom/sofa ...]

A revision older than a method entry point installed now (``naka-gs-fast`` came after 023ceac) gets, in its
worktree only, that name bound to its ``naka_gs_method``, so that nerfstudio's entry points resolve; the
bench says so. Uncommitted changes are not measured: commit them, or name the revision that has them.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import tyro

from benchmarks.harness import timed
from benchmarks.machine import describe_cpu

REPO = Path(__file__).resolve().parents[1]
NS_BIN = Path(sys.executable).parent
"""Where ``ns-train`` and ``ns-eval`` of the environment running this bench live."""
LOM = Path("../shared/data/lom")
STEP_LINE = re.compile(r"^(\d+) \(\s*[\d.]+%\)\s+(?:(\d+) s, )?([\d.]+) (ms|s)\b", re.MULTILINE)
"""nerfstudio's progress line: step, then the step time as ``12.3 ms``, ``1 s, 23.4 ms`` or ``1.2 s``."""
COMPILE_LINE = re.compile(r"kernels compiled \(and cached on disk\)[\s\S]{0,200}?\bin ([\d.]+) s")
"""cpu-fast's log line of a first run's kernel compile (rich may wrap it and add its source location)."""


@dataclass
class Args:
    old: str
    """Git revision of the tree to compare against (e.g. 023ceac, main when issue 34 was filed)."""
    new: str = "HEAD"
    """Git revision of the tree measured."""
    scenes: Tuple[Path, ...] = tuple(LOM / name for name in ("sofa", "bike", "chair", "shrub"))
    """Scene folders (lowlight-data layout), read in place."""
    method: str = "naka-gs"
    steps: Optional[int] = None
    """``--max-num-iterations`` for both sides (default: the method's own)."""
    phases: Tuple[int, ...] = (500, 3250, 6500, 7000)
    """Step boundaries of the phases whose median step time is printed (the CPU schedule's: 1/4, 1/2, full size)."""
    work: Optional[Path] = None
    """Work folder for the worktrees, caches, logs and runs (default: a new temporary one); kept afterwards."""


def step_times(log_text: str) -> Dict[int, float]:
    """Step -> ms of the step times ``ns-train`` printed (the last one printed for each step)."""
    times = {}
    for step, seconds, value, unit in STEP_LINE.findall(log_text):
        times[int(step)] = (int(seconds or 0) * 1000.0) + float(value) * (1000.0 if unit == "s" else 1.0)
    return times


def phase_medians(times: Dict[int, float], phases: Sequence[int]) -> List[Optional[float]]:
    """Median ms per step of each phase: steps in [phases[0], phases[1]], then (phases[i], phases[i + 1]]."""
    medians = []
    for i in range(len(phases) - 1):
        lo, hi = phases[i], phases[i + 1]
        picked = [t for s, t in times.items() if (lo <= s if i == 0 else lo < s) and s <= hi]
        medians.append(statistics.median(picked) if picked else None)
    return medians


def missing_entry_points(tree: Path) -> List[str]:
    """Names that this environment's naka-gs method entry points give which ``tree``'s modules lack."""
    wanted = [
        ep for ep in metadata.entry_points(group="nerfstudio.method_configs") if ep.module.startswith("naka_gs_plugin.")
    ]
    probe = "import importlib\n" + "".join(
        f"if not hasattr(importlib.import_module({ep.module!r}), {ep.attr!r}): print({ep.value!r})\n" for ep in wanted
    )
    env = dict(os.environ, PYTHONPATH=str(tree))
    # From inside the tree: ``python -c`` puts its working directory first on sys.path.
    out = subprocess.run([sys.executable, "-c", probe], env=env, cwd=tree, capture_output=True, text=True, check=True)
    return out.stdout.split()


def checkout(revision: str, path: Path) -> str:
    """A detached worktree of ``revision`` at ``path``; its short hash. Entry points it lacks are bound to its
    default method (module docstring)."""
    # A worktree whose folder was deleted (an interrupted run's work folder) stays registered, and git then
    # refuses to add one at that path again.
    subprocess.run(["git", "-C", str(REPO), "worktree", "prune"], check=True, capture_output=True)
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(path), revision], check=True,
                   capture_output=True)  # fmt: skip
    short = subprocess.run(["git", "-C", str(path), "rev-parse", "--short", "HEAD"], check=True, capture_output=True,
                           text=True).stdout.strip()  # fmt: skip
    for value in missing_entry_points(path):
        module, attr = value.split(":")
        source = path / (module.replace(".", "/") + ".py")
        with open(source, "a") as fh:
            fh.write(f"\n{attr} = naka_gs_method  # added by benchmarks.wall_ab: an entry point installed now\n")
        print(f"  {revision} ({short}) lacks {value}: bound to its naka_gs_method in the worktree")
    return short


def run_side(tree: Path, side: str, scene: Path, args: Args, work: Path) -> Dict:
    """One ``ns-train`` from ``tree`` with empty caches, then its ``ns-eval``; the figures of the row."""
    run_dir = work / side / scene.name
    caches = {name: run_dir / name for name in ("naka-gs-cache", "numba-cache")}
    for folder in caches.values():
        folder.mkdir(parents=True)
    env = dict(os.environ, PYTHONPATH=str(tree), NAKA_GS_CACHE=str(caches["naka-gs-cache"]),
               NUMBA_CACHE_DIR=str(caches["numba-cache"]))  # fmt: skip
    train = [str(NS_BIN / "ns-train"), args.method, "--data", str(scene), "--vis", "tensorboard",
             "--output-dir", str(run_dir / "outputs"), "--timestamp", "run"]  # fmt: skip
    if args.steps is not None:
        train += ["--max-num-iterations", str(args.steps)]
    log = run_dir / "ns-train.log"
    wall, rss = timed(train, env, log)
    config = next((run_dir / "outputs").glob(f"*/{args.method}/run/config.yml"))
    scores_path = run_dir / "eval.json"
    evaluate = [str(NS_BIN / "ns-eval"), "--load-config", str(config), "--output-path", str(scores_path)]
    timed(evaluate, env, run_dir / "ns-eval.log")
    scores = json.loads(scores_path.read_text())["results"]
    text = log.read_text(errors="replace")
    compiled = COMPILE_LINE.findall(text)
    return dict(
        wall=wall,
        rss=rss,
        compile=float(compiled[0]) if compiled else None,
        phases=phase_medians(step_times(text), args.phases),
        scores=tuple(scores.get(k) for k in ("psnr", "ssim", "lpips")),
    )


def _ms(values: Sequence[Optional[float]]) -> str:
    return " / ".join("-" if v is None else f"{v:.1f}" for v in values)


def _scores(values: Sequence[Optional[float]]) -> str:
    return " / ".join("-" if v is None else f"{v:.{d}f}" for v, d in zip(values, (2, 4, 4)))


def main(args: Args) -> List[Tuple[str, Dict, Dict]]:
    missing = [str(s) for s in args.scenes if not (s / "transforms_train.json").is_file()]
    if missing:
        sys.exit(f"--scenes: no transforms_train.json in {', '.join(missing)} -- give lowlight-data scene folders")
    if len(args.phases) < 2 or list(args.phases) != sorted(args.phases):
        sys.exit("--phases: give at least two increasing step numbers")
    if not Path("/usr/bin/time").exists():
        sys.exit("benchmarks.wall_ab needs GNU time (/usr/bin/time): apt-get install time")
    for option, revision in (("--old", args.old), ("--new", args.new)):
        known = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", f"{revision}^{{commit}}"],
                               capture_output=True)  # fmt: skip
        if known.returncode != 0:
            sys.exit(f"{option} {revision}: not a commit of {REPO} -- give a hash, branch or tag (git log)")
    work = args.work or Path(tempfile.mkdtemp(prefix="naka-gs-wall-ab-"))
    trees = {side: work / f"tree-{side}" for side in ("old", "new")}
    used = [str(work / name) for name in ("tree-old", "tree-new", "old", "new") if (work / name).exists()]
    if used:
        sys.exit(f"--work {work}: holds an earlier run ({', '.join(used)}) -- give a new folder")
    work.mkdir(parents=True, exist_ok=True)
    print(describe_cpu())
    try:
        hashes = {side: checkout(rev, trees[side]) for side, rev in (("old", args.old), ("new", args.new))}
        print(f"old {args.old} ({hashes['old']}), new {args.new} ({hashes['new']}), `ns-train {args.method}`, "
              f"empty caches per run; work folder {work}", flush=True)  # fmt: skip
        rows = []
        for i, scene in enumerate(args.scenes):
            result = {}
            for side in ("old", "new") if i % 2 == 0 else ("new", "old"):
                result[side] = run_side(trees[side], side, scene, args, work)
                print(f"  {scene.name} {side}: {result[side]['wall']:.1f} s", flush=True)
            rows.append((scene.name, result["old"], result["new"]))
    finally:
        for tree in trees.values():
            if tree.exists():
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)
    phases = ", ".join(f"{a}-{b}" for a, b in zip(args.phases, args.phases[1:]))
    print(f"\n| scene | old wall s (peak RSS GB) | new wall s (peak RSS GB) | new / old | ms per step, steps {phases}, "
          "old -> new | kernel compile s, old -> new | ns-eval PSNR / SSIM / LPIPS, old -> new |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for name, old, new in rows:
        compile_s = " -> ".join("-" if r["compile"] is None else f"{r['compile']:.1f}" for r in (old, new))
        print(f"| {name} | {old['wall']:.1f} ({old['rss']:.2f}) | {new['wall']:.1f} ({new['rss']:.2f}) | "
              f"{new['wall'] / old['wall']:.3f} | {_ms(old['phases'])} -> {_ms(new['phases'])} | {compile_s} | "
              f"{_scores(old['scores'])} -> {_scores(new['scores'])} |")  # fmt: skip
    mean_old = statistics.mean(old["wall"] for _, old, _ in rows)
    mean_new = statistics.mean(new["wall"] for _, _, new in rows)
    ratios = [new["wall"] / old["wall"] for _, old, new in rows]
    print(f"| **mean** | {mean_old:.1f} | {mean_new:.1f} | **{mean_new / mean_old:.3f}** (mean of the ratios "
          f"{statistics.mean(ratios):.3f}) | | | |")  # fmt: skip
    return rows


def entrypoint(argv: Optional[Sequence[str]] = None) -> List[Tuple[str, Dict, Dict]]:
    return main(tyro.cli(Args, args=argv))


if __name__ == "__main__":
    entrypoint()
