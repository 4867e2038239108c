"""``naka-gs-sim-stats --sets LABEL=GLOB ...``: image statistics of simulated and real low-light captures.

The statistics are described in :mod:`naka_gs_plugin.sim.stats`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import tyro

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.sim.stats import pick, seed_noise_line, set_stats


@dataclass
class SimStats:
    """Print a markdown table of low-light image statistics per set of training images."""

    sets: List[str] = field(default_factory=list)
    """``label=glob`` pairs of training images, e.g. realx3d='../shared/data/realx3d/*/train/*.JPG'."""
    seed_pairs: List[str] = field(default_factory=list)
    """``label=DIR1,DIR2``: the same training views generated with two seeds (noise line from their difference)."""
    per_folder: int = 3
    """Images used per folder matched by a glob (or per seed pair)."""

    def main(self) -> Dict[str, Dict[str, float]]:
        """Print a markdown table of :func:`set_stats` per set and return it."""
        pairs = [item.split("=", 1) for item in self.sets]
        table = {label: set_stats(pick(pattern, self.per_folder)) for label, pattern in pairs}
        for item in self.seed_pairs:
            label, dirs = item.split("=", 1)
            first, second = (Path(d) for d in dirs.split(","))
            files = [(p, second / p.name) for p in sorted(first.iterdir())[: self.per_folder]]
            slope, intercept = seed_noise_line(files)
            if label in table:
                mean = table[label]["mean"]
            else:
                mean = float(np.mean([read_rgb(p, np.float64).mean() for p, _ in files]))
            std = float(np.sqrt(max(slope * mean + intercept, 0.0)))
            table[f"{label} (2 seeds)"] = {
                **table.get(label, {"n_images": len(files), "mean": mean, "saturated_pct": float("nan")}),
                "noise_slope": slope,
                "noise_intercept": intercept,
                "noise_std_at_mean": std,
            }
        print("| set | images | mean | sat % | var slope | var intercept | noise std @ mean |")
        print("|---|---|---|---|---|---|---|")
        for label, s in table.items():
            print(
                f"| {label} | {s['n_images']} | {s['mean']:.4f} | {s['saturated_pct']:.2f} | "
                f"{s['noise_slope']:.2e} | {s['noise_intercept']:.2e} | {s['noise_std_at_mean']:.4f} |"
            )
        return table


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-sim-stats``."""
    tyro.cli(SimStats, args=args).main()


if __name__ == "__main__":
    entrypoint()
