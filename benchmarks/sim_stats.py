"""Image statistics of low-light training images, to compare simulated scenes with real captures.

Per image, on **stored values** in [0, 1] (sRGB for real JPEGs and sRGB-response scenes; linear
for scenes written without a ``response``): mean brightness, % saturated pixels (any channel
>= 254/255), and a noise line ``var = slope * mean + intercept`` of the grey (channel-mean) image
fitted on flat patches:
8x8 patches of the high-pass residual ``x - box3x3(x)`` (variance x 9/8 = pixel noise variance),
binned by patch mean; the 10th percentile of each bin's variances stands for the flat patches.
Brightness and saturation use the image box-downscaled to at most ``max_side`` px; the noise fit
uses a central full-resolution crop (downscaling would average the noise away).

    python -m benchmarks.sim_stats --sets dark-noisy='/tmp/sim/dark-noisy/train/*.png' \
        realx3d='../shared/data/realx3d/*/train/*.JPG' \
        --seed-pairs dark-noisy=/tmp/sim/dark-noisy/train,/tmp/sim1/dark-noisy/train

The flat-patch fit has a floor from texture on small synthetic images (about 0.009 on the noise-free
``clean`` scene at 160x120); the two-seed fit (:func:`seed_noise_line`) measures simulated noise exactly.

Run from the repository root: ``python -m benchmarks.sim_stats --help``.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import tyro
from jaxtyping import Float

from naka_gs_plugin.data.images import read_rgb


@dataclass
class ImageStats:
    mean: float
    saturated_pct: float
    noise_slope: float
    noise_intercept: float
    noise_std_at_mean: float


def noise_line(img: Float[np.ndarray, "H W 3"], patch: int = 8, bins: int = 12) -> tuple:
    """``(slope, intercept)`` of variance vs mean on flat patches of the (grey) image."""
    grey = img.mean(-1)
    pad = np.pad(grey, 1, mode="edge")
    box = sum(pad[i : i + grey.shape[0], j : j + grey.shape[1]] for i in range(3) for j in range(3)) / 9.0
    resid = grey - box
    h, w = (grey.shape[0] // patch) * patch, (grey.shape[1] // patch) * patch

    def tiles(a: np.ndarray) -> np.ndarray:
        return a[:h, :w].reshape(h // patch, patch, w // patch, patch).swapaxes(1, 2).reshape(-1, patch * patch)

    means, varis = tiles(grey).mean(1), tiles(resid).var(1) * 9.0 / 8.0
    keep = (means > 0.002) & (means < 0.95)
    means, varis = means[keep], varis[keep]
    if len(means) < 2 * bins:
        return float("nan"), float("nan")
    edges = np.quantile(means, np.linspace(0, 1, bins + 1))
    xs, ys = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (means >= lo) & (means <= hi)
        if sel.sum() >= 4:
            xs.append(means[sel].mean())
            ys.append(np.percentile(varis[sel], 10))
    slope, intercept = np.polyfit(xs, ys, 1)
    return float(slope), float(intercept)


def seed_noise_line(pairs: List[tuple], bins: int = 12) -> tuple:
    """``(slope, intercept)`` of variance vs mean from the same views rendered with two noise seeds.

    Per pixel of the grey (channel-mean) images, as :func:`noise_line`, ``(a - b)**2 / 2`` estimates
    the noise variance at level ``(a + b) / 2`` (stored values); binned by level (only pixels that
    are neither saturated nor black in any channel), then a line is fitted.
    Free of texture, unlike :func:`noise_line`; needs a second generation (``naka-gs-sim --seed``).
    """
    a = np.concatenate([read_rgb(p, np.float64).reshape(-1, 3) for p, _ in pairs])
    b = np.concatenate([read_rgb(q, np.float64).reshape(-1, 3) for _, q in pairs])
    keep = (np.maximum(a, b).max(1) < 254.0 / 255.0) & (np.minimum(a, b).min(1) > 0.0)
    a, b = a.mean(1)[keep], b.mean(1)[keep]
    level, var = (a + b) / 2, (a - b) ** 2 / 2
    edges = np.quantile(level, np.linspace(0, 1, bins + 1))
    idx = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, bins - 1)
    xs = np.array([level[idx == i].mean() for i in range(bins) if (idx == i).sum() > 50])
    ys = np.array([var[idx == i].mean() for i in range(bins) if (idx == i).sum() > 50])
    slope, intercept = np.polyfit(xs, ys, 1)
    return float(slope), float(intercept)


def image_stats(path: Path, max_side: int = 400, crop: int = 512) -> ImageStats:
    img = read_rgb(path, np.float64)
    h, w = img.shape[:2]
    factor = max(1, int(np.ceil(max(h, w) / max_side)))
    small = img[: h // factor * factor, : w // factor * factor]
    small = small.reshape(h // factor, factor, w // factor, factor, 3).mean((1, 3))
    y0, x0 = max(0, (h - crop) // 2), max(0, (w - crop) // 2)
    slope, intercept = noise_line(img[y0 : y0 + crop, x0 : x0 + crop])
    mean = float(small.mean())
    full_sat = float((img >= 254.0 / 255.0).any(-1).mean() * 100.0)
    return ImageStats(mean, full_sat, slope, intercept, float(np.sqrt(max(slope * mean + intercept, 0.0))))


def set_stats(paths: List[Path]) -> Dict[str, float]:
    """Averages of :func:`image_stats` over ``paths``."""
    rows = [image_stats(p) for p in paths]
    out = {k: float(np.nanmean([getattr(r, k) for r in rows])) for k in ImageStats.__dataclass_fields__}
    return {"n_images": len(rows), **out}


def pick(pattern: str, per_folder: int) -> List[Path]:
    """The first ``per_folder`` files (sorted) of each folder matched by the glob ``pattern``."""
    by_dir: Dict[Path, List[Path]] = {}
    for p in sorted(Path(x) for x in glob.glob(pattern)):
        by_dir.setdefault(p.parent, []).append(p)
    return [p for files in by_dir.values() for p in files[:per_folder]]


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
    """``python -m benchmarks.sim_stats``."""
    tyro.cli(SimStats, args=args).main()


if __name__ == "__main__":
    entrypoint()
