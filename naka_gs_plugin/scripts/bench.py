"""``naka-gs-bench GRID``: what accuracy costs in time, as a resumable grid of training runs.

The grid format, the runs and the outputs are described in :mod:`naka_gs_plugin.bench.grid`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.bench.grid import (
    BenchSpecError,
    execute,
    grid_runs,
    load_grid,
    machine_description,
    markdown_table,
    plot,
)
from naka_gs_plugin.progress import StageProgress


@dataclass
class Bench:
    """Run (or resume) an accuracy-vs-time grid and write its table and plots."""

    grid: tyro.conf.Positional[Path]
    """Grid file, e.g. configs/bench/cpu.yaml."""
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
        if not self.report_only:
            runs = [
                r for r in grid_runs(spec, out) if not self.only or r["id"] in self.only or r["family"] in self.only
            ]
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
        return results


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-bench``; a bad grid prints one line and exits with status 2."""
    try:
        tyro.cli(Bench, args=args).main()
    except BenchSpecError as err:
        CONSOLE.print(f"[naka-gs bench] error: {err}", markup=False)
        raise SystemExit(2) from None


if __name__ == "__main__":
    entrypoint()
