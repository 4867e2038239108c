"""PPM runtime benchmark: voxel pooling + progressive pruning on the issue's synthetic clouds.

Cloud (x ``--scale``): 700k points on the surface z = 0.1 sin(3x) over [-1, 1]^2, 250k in a
sigma = 0.002 cluster and 50k uniform outliers in [-3, 3]^3, seed 0, shuffled. Each size runs in a
fresh process so peak RSS (``ru_maxrss``) is its own; the figure printed is the increase caused by
``run_ppm`` (input generation excluded). Reference on the 2-core dev machine (the authors' PPM,
same defaults): 1.41 s on 1M points and 9.75 s on 6M.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Sequence, Tuple

import numpy as np
import tyro

REFERENCE_SECONDS = {1: 1.41, 6: 9.75}


def make_cloud(scale: int, seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """The benchmark cloud described in the module docstring (normalized scene units)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (700_000 * scale, 2))
    surface = np.c_[xy, 0.1 * np.sin(3 * xy[:, 0])]
    cluster = rng.normal([0.2, 0.1, 0.1 * np.sin(0.6)], 0.002, (250_000 * scale, 3))
    outliers = rng.uniform(-3, 3, (50_000 * scale, 3))
    xyz = np.concatenate([surface, cluster, outliers])
    rgb = rng.integers(0, 256, xyz.shape, dtype=np.uint8)
    perm = rng.permutation(len(xyz))
    return xyz[perm], rgb[perm]


def run_one(scale: int) -> dict:
    """Time ``run_ppm`` on one cloud in this process."""
    from naka_gs_plugin.points.ppm import run_ppm

    xyz, rgb = make_cloud(scale)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    _, _, summary = run_ppm(xyz, rgb)
    seconds = time.perf_counter() - start
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "points": len(xyz),
        "seconds": seconds,
        "timings_s": summary["timings_s"],
        "voxels": summary["voxel_count"],
        "kept": summary["final_count"],
        "peak_rss_increase_gb": (rss_after - rss_before) / 1e6,
        "load_average": os.getloadavg()[0],
    }


@dataclass
class PPMBench:
    """Time PPM on the 1M / 6M benchmark clouds, each in a fresh process."""

    scales: Tuple[int, ...] = (1, 6)
    """Cloud sizes in millions of points."""

    def main(self) -> None:
        for scale in self.scales:
            out = subprocess.run(
                [sys.executable, "-m", "naka_gs_plugin.bench.ppm_bench", "--child", str(scale)],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            r = json.loads(out.strip().splitlines()[-1])
            ref = REFERENCE_SECONDS.get(scale)
            speedup = f", {ref / r['seconds']:.1f}x faster than the reference {ref} s" if ref else ""
            print(
                f"{r['points']:,} points: {r['seconds']:.3f} s (pool {r['timings_s']['voxel_pool']:.3f} s, "
                f"prune {r['timings_s']['prune']:.3f} s){speedup}; {r['voxels']:,} voxels, {r['kept']:,} kept; "
                f"peak RSS +{r['peak_rss_increase_gb']:.2f} GB; load {r['load_average']:.2f}"
            )


def main(args: Sequence[str] | None = None) -> None:
    argv = list(sys.argv[1:] if args is None else args)
    if argv[:1] == ["--child"]:
        print(json.dumps(run_one(int(argv[1]))))
        return
    tyro.cli(PPMBench, args=argv).main()


if __name__ == "__main__":
    main()
