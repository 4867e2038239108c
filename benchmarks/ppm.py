"""PPM runtime benchmark: ours against a plain re-implementation of the authors' PPM, in one run.

Cloud (x ``--scale``): 700k points on the surface z = 0.1 sin(3x) over [-1, 1]^2, 250k in a
sigma = 0.002 cluster and 50k uniform outliers in [-3, 3]^3, seed 0, shuffled. Each (implementation,
size) runs in a fresh process so its peak RSS is its own (:mod:`benchmarks.harness`); the
figure printed is the increase caused by the PPM call (input generation excluded). The reference, :func:`reference_ppm`,
is the authors' algorithm as documented (``method-facts.md`` section 5) written the plain NumPy /
SciPy way: ``np.unique`` voxel keys, ``np.add.at`` sums, a fresh ``cKDTree`` every iteration. Both
produce the same points (checked); the printed ratio is measured here, on this CPU.

Run from the repository root: ``python -m benchmarks.ppm --help``.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import tyro

from benchmarks.harness import peak_rss, reset_peak_rss, run_isolated
from benchmarks.machine import describe_cpu


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


def reference_ppm(
    xyz: np.ndarray,
    rgb: np.ndarray,
    voxel: float = 0.01,
    tau0: float = 0.005,
    beta: float = 0.01,
    iterations: int = 6,
    min_points: int = 5000,
    eps: float = 1e-8,
    seed: int = 42,
) -> Tuple[np.ndarray, np.ndarray]:
    """The authors' PPM, plainly: voxel means (colour rounded half-up), then up to ``iterations``
    rounds of keep-with-probability ``min(1, d_nn / (tau + eps))`` from one ``default_rng(seed)``
    stream, rolled back and stopped below ``min_points``, ``tau *= exp(beta * N_before / M0)``."""
    from scipy.spatial import cKDTree

    keys = np.floor(xyz / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, xyz)
    csum = np.zeros((len(counts), 3), np.int64)
    np.add.at(csum, inverse, rgb.astype(np.int64))
    pts = sums / counts[:, None]
    cols = ((2 * csum + counts[:, None]) // (2 * counts[:, None])).astype(np.uint8)
    rng = np.random.default_rng(seed)
    tau, m0 = tau0, len(pts)
    for _ in range(iterations):
        if len(pts) <= 1:
            break
        d = cKDTree(pts).query(pts, k=2)[0][:, 1]
        keep = rng.random(len(pts)) < np.minimum(1.0, d / (tau + eps))
        if keep.sum() < min_points:
            break
        n_before = len(pts)
        pts, cols = pts[keep], cols[keep]
        tau *= math.exp(beta * n_before / m0)
    return pts, cols


def run_one(scale: int, impl: str) -> dict:
    """Time one PPM implementation (``ours`` or ``reference``) on one cloud in this process."""
    from naka_gs_plugin.points.ppm import run_ppm

    xyz, rgb = make_cloud(scale)
    rss_before = reset_peak_rss()
    start = time.perf_counter()
    if impl == "ours":
        pts, _, summary = run_ppm(xyz, rgb)
    else:
        pts, _ = reference_ppm(xyz, rgb)
    seconds = time.perf_counter() - start
    rss_after = peak_rss()
    order = np.lexsort(pts.T[::-1])
    return {
        "impl": impl,
        "points": len(xyz),
        "seconds": seconds,
        "kept": len(pts),
        "checksum": float(np.round(pts[order][:: max(1, len(pts) // 1000)].sum(), 6)),
        "timings_s": summary["timings_s"] if impl == "ours" else None,
        "peak_rss_increase_gb": (rss_after - rss_before) / 1e9,
        "load_average": os.getloadavg()[0],
    }


def compare(scales: Sequence[int], reference: bool) -> None:
    """Print ours (and the reference) per cloud size in millions of points, each in a fresh process."""
    print(describe_cpu())
    for scale in scales:
        runs = {}
        for impl in ("ours", "reference") if reference else ("ours",):
            runs[impl] = run_isolated(run_one, scale, impl)
        r = runs["ours"]
        line = (
            f"{r['points']:,} points: ours {r['seconds']:.3f} s (pool {r['timings_s']['voxel_pool']:.3f} s, "
            f"prune {r['timings_s']['prune']:.3f} s), {r['kept']:,} kept, peak RSS +{r['peak_rss_increase_gb']:.2f} GB"
        )
        if "reference" in runs:
            ref = runs["reference"]
            same = "same points" if (ref["kept"], ref["checksum"]) == (r["kept"], r["checksum"]) else "POINTS DIFFER"
            line += (
                f"; reference {ref['seconds']:.3f} s, peak RSS +{ref['peak_rss_increase_gb']:.2f} GB: "
                f"ours {ref['seconds'] / r['seconds']:.1f}x faster ({same})"
            )
        print(f"{line}; load {r['load_average']:.2f}", flush=True)


@dataclass
class BenchPpm:
    """Time our PPM and the plain reference on the 1M / 6M benchmark clouds, each in a fresh process."""

    scales: Tuple[int, ...] = (1, 6)
    """Cloud sizes in millions of points."""
    reference: bool = True
    """Also run the plain re-implementation of the authors' PPM (the ratio's denominator)."""

    def main(self) -> None:
        compare(self.scales, self.reference)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.ppm``."""
    tyro.cli(BenchPpm, args=args).main()


if __name__ == "__main__":
    entrypoint()
