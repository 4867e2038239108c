"""Benchmark the sparse pure-torch rasterizer against the dense reference.

Every case (method x Gaussians x resolution) runs in a fresh spawned process, so each one's peak
memory is its own: "peak MB" is the kernel's peak resident set size of the process (``VmHWM``,
reset through ``/proc/self/clear_refs`` just before the first render) minus its resident size at
that moment, i.e. the extra host memory the renders (forward and backward, including allocator
caches) needed at their peak. (``getrusage``'s ``ru_maxrss`` would be wrong here: Linux carries the
parent's value across fork and exec.) On CUDA it is ``torch.cuda.max_memory_allocated`` instead.
Timings are only meaningful on an otherwise idle machine; the load averages at the start and end
are recorded with the results.

The dense reference materialises pixels x Gaussians tensors, so unless that product fits
``--dense-budget`` it is not run on the full image. Its cost is ``t0 + k * pixels``; it is timed on
a 1-pixel image and on a top-left window of the same camera (same intrinsics, smaller image) with
pixels x Gaussians within the budget, and that line is extrapolated to the full image. Such rows
are marked with ``*`` and the window size; their memory is that of the window.

The scene imitates a trained splatfacto scene: Gaussians spread through the view frustum at depths
2..10 (60 degree horizontal field of view), random orientations, log-normal anisotropic scales
(sigma 0.6 in log space per axis) whose median projects to a 0.6 px standard deviation at the mean
depth at 441 px width, i.e. a mean radius of ~4.7 px after gsplat's 0.3 px^2 blur (sizes grow with
the resolution, as when rendering one scene larger), sigmoid(N(0, 2)) opacities and degree-3 SH
colours. The table reports the mean radius of the visible Gaussians and the number of
Gaussian-pixel pairs with ``alpha >= 1/255`` inside the radius boxes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import os
import statistics
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
import tyro
from rich.console import Console
from rich.table import Table

SH_DEGREE = 3
FOV_X_DEG = 60.0
REFERENCE_WIDTH = 441
MEDIAN_SIGMA_PX = 0.6
"""Median projected standard deviation (px) of a Gaussian axis at the mean depth at 441 px width."""


@dataclasses.dataclass
class BenchConfig:
    """Sparse vs dense rasterizer timing (forward, forward+backward) and peak memory."""

    sizes: Tuple[int, ...] = (10_000, 50_000, 100_000)
    """Numbers of Gaussians."""
    resolutions: Tuple[str, ...] = ("220x146", "441x293", "882x586")
    """Image sizes as WIDTHxHEIGHT."""
    repeats: int = 3
    """Timed repetitions per case after one warm-up; the median is reported."""
    threads: int = 2
    """torch intra-op threads."""
    dense_budget: int = 20_000_000
    """Largest pixels x Gaussians product the dense reference renders in one go."""
    device: str = "cpu"
    """Torch device, e.g. cpu or cuda."""
    quick: bool = False
    """Smoke run: 10k Gaussians at 220x146, one repetition."""
    out_json: Optional[Path] = None
    """Also write the results here."""


def make_scene(n: int, width: int, height: int, seed: int = 0, device: str = "cpu") -> Dict:
    """Random trained-scene-like Gaussians in front of one OpenCV camera at the origin."""
    gen = torch.Generator().manual_seed(seed)
    focal = 0.5 * width / math.tan(math.radians(FOV_X_DEG) / 2)
    depth = 2.0 + 8.0 * torch.rand(n, generator=gen)
    # Spread 10 % beyond the frustum so that some Gaussians straddle or miss the image.
    x = (torch.rand(n, generator=gen) - 0.5) * 1.1 * width / focal * depth
    y = (torch.rand(n, generator=gen) - 0.5) * 1.1 * height / focal * depth
    focal_ref = 0.5 * REFERENCE_WIDTH / math.tan(math.radians(FOV_X_DEG) / 2)
    median_scale = MEDIAN_SIGMA_PX * 6.0 / focal_ref  # world units at the mean depth 6
    log_scales = math.log(median_scale) + 0.6 * torch.randn(n, 3, generator=gen)
    k = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    scene = {
        "means": torch.stack([x, y, depth], dim=1),
        "quats": torch.randn(n, 4, generator=gen),
        "scales": torch.exp(log_scales),
        "opacities": torch.sigmoid(2.0 * torch.randn(n, generator=gen)),
        "colors": 0.3 * torch.randn(n, (SH_DEGREE + 1) ** 2, 3, generator=gen),
        "viewmats": torch.eye(4)[None],
        "Ks": k[None],
    }
    return {key: value.to(device) for key, value in scene.items()}


@torch.no_grad()
def scene_stats(scene: Dict, width: int, height: int) -> Tuple[float, int]:
    """Mean radius (px) of the visible Gaussians and their number of ``alpha >= 1/255`` box pixels."""
    from naka_gs_plugin.model.projection import pixel_bounds, project_gaussians
    from naka_gs_plugin.model.rasterize import ALPHA_MAX, ALPHA_MIN

    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], width, height
    )
    visible = proj.radii[0] > 0
    box = pixel_bounds(proj.means2d, proj.radii, width, height)[0][visible]
    means2d, conics = proj.means2d[0][visible], proj.conics[0][visible]
    opacities = scene["opacities"][visible]
    side = torch.maximum(box[:, 1] - box[:, 0], box[:, 3] - box[:, 2]).clamp(min=0) + 1
    pairs = 0
    for size in torch.unique(side).tolist():  # equal-sized boxes together, ~4M pixels at a time
        group = torch.nonzero(side == size).squeeze(1)
        step = max(1, (1 << 22) // (size * size))
        for lo in range(0, len(group), step):
            idx = group[lo : lo + step]
            b, m, c, o = box[idx], means2d[idx], conics[idx], opacities[idx]
            offsets = torch.arange(size, device=b.device)
            xs, ys = b[:, 0:1] + offsets, b[:, 2:3] + offsets  # [n, size]
            dx = (m[:, 0:1] - xs - 0.5)[:, None, :]
            dy = (m[:, 1:2] - ys - 0.5)[:, :, None]
            sigma = 0.5 * (c[:, 0, None, None] * dx * dx + c[:, 2, None, None] * dy * dy)
            sigma = sigma + c[:, 1, None, None] * dx * dy
            alpha = torch.clamp_max(o[:, None, None] * torch.exp(-sigma), ALPHA_MAX)
            inside = (xs <= b[:, 1:2])[:, None, :] & (ys <= b[:, 3:4])[:, :, None]
            pairs += int((inside & (sigma >= 0) & (alpha >= ALPHA_MIN)).sum())
    return float(proj.radii[0][visible].float().mean()), pairs


def _proc_status_bytes(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024  # reported in kB
    raise RuntimeError(f"{field} missing from /proc/self/status")


def _reset_peak_rss() -> int:
    """Reset the kernel's peak-RSS mark of this process to its current RSS, and return that."""
    with open("/proc/self/clear_refs", "w") as clear_refs:
        clear_refs.write("5")
    return _proc_status_bytes("VmRSS")


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _time_renders(scene: Dict, width: int, height: int, method: str, repeats: int, device: str):
    """Median forward and forward+backward seconds of ``repeats`` renders after one warm-up."""
    from naka_gs_plugin.model.rasterize import rasterization
    from naka_gs_plugin.model.rasterize_dense import rasterization_dense

    render = rasterization if method == "sparse" else rasterization_dense
    fwd, total = [], []
    for _ in range(repeats + 1):
        params = {k: v.detach().clone().requires_grad_(k not in ("viewmats", "Ks")) for k, v in scene.items()}
        _sync(device)
        t0 = time.perf_counter()
        colors, alphas, _ = render(**params, width=width, height=height, sh_degree=SH_DEGREE)
        _sync(device)
        t1 = time.perf_counter()
        (colors.square().mean() + alphas.mean()).backward()
        _sync(device)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        total.append(t2 - t0)
        del colors, alphas, params
    return statistics.median(fwd[1:]), statistics.median(total[1:])


def _run_case(method: str, n: int, width: int, height: int, cfg: BenchConfig) -> Dict:
    """One benchmark case, meant to run in a fresh process (its peak memory is its own)."""
    torch.set_num_threads(cfg.threads)
    scene = make_scene(n, width, height, device=cfg.device)
    if cfg.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        base = _reset_peak_rss()
    result: Dict = {"method": method, "gaussians": n, "width": width, "height": height}
    if method == "sparse" or n * width * height <= cfg.dense_budget:
        result["fwd_s"], result["fwd_bwd_s"] = _time_renders(scene, width, height, method, cfg.repeats, cfg.device)
        result["measured_pixels"] = width * height
    else:
        # Dense cost is t0 + k * pixels: measure a 1-pixel and a budget-sized top-left window of the
        # same camera (same K, smaller image) and extrapolate the line to the full image.
        pixels = max(2, cfg.dense_budget // n)
        win_w = min(width, pixels)
        win_h = max(1, min(height, pixels // win_w))
        one = _time_renders(scene, 1, 1, method, cfg.repeats, cfg.device)
        window = _time_renders(scene, win_w, win_h, method, cfg.repeats, cfg.device)
        scale = (width * height - 1) / (win_w * win_h - 1)
        result["fwd_s"], result["fwd_bwd_s"] = (o + (w - o) * scale for o, w in zip(one, window))
        result["measured_pixels"] = win_w * win_h
        result["window"] = f"{win_w}x{win_h}"
    if cfg.device.startswith("cuda"):
        result["peak_mb"] = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:
        result["peak_mb"] = (_proc_status_bytes("VmHWM") - base) / 2**20
    return result


def _run_isolated(pool_ctx, *args) -> Dict:
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=1, mp_context=pool_ctx) as pool:
        return pool.submit(_run_case, *args).result()


def run_cases(cfg: BenchConfig) -> List[Dict]:
    """Run every case, each in a fresh spawned process; returns one dict per (size, resolution)."""
    torch.set_num_threads(cfg.threads)
    ctx = multiprocessing.get_context("spawn")
    rows = []
    console = Console(stderr=True)
    for res in cfg.resolutions:
        width, height = (int(v) for v in res.lower().split("x"))
        for n in cfg.sizes:
            radius, pairs = scene_stats(make_scene(n, width, height), width, height)
            row = {"gaussians": n, "resolution": res, "mean_radius_px": radius, "pairs": pairs}
            for method in ("sparse", "dense"):
                console.log(f"{method} {n} Gaussians at {res} ...")
                row[method] = _run_isolated(ctx, method, n, width, height, cfg)
            row["speedup_fwd"] = row["dense"]["fwd_s"] / row["sparse"]["fwd_s"]
            row["speedup_fwd_bwd"] = row["dense"]["fwd_bwd_s"] / row["sparse"]["fwd_bwd_s"]
            rows.append(row)
    return rows


def render_table(rows: List[Dict], cfg: BenchConfig) -> Table:
    table = Table(
        title=f"Rasterizer benchmark ({cfg.device}, {cfg.threads} threads, median of {cfg.repeats})",
        caption=(
            "peak MB: peak RSS (VmHWM) minus RSS before rendering, per case in a fresh process. "
            "dense*: extrapolated linearly in pixels from a 1-pixel and the stated window of the same "
            "camera (pixels x Gaussians <= --dense-budget); its peak MB is that of the window."
        ),
    )
    for col in (
        "Gaussians",
        "image",
        "mean r px",
        "pairs",
        "sparse fwd s",
        "sparse f+b s",
        "sparse MB",
        "dense fwd s",
        "dense f+b s",
        "dense MB",
        "dense measured",
        "speed-up fwd",
        "speed-up f+b",
    ):
        table.add_column(col, justify="right")
    for row in rows:
        sparse, dense = row["sparse"], row["dense"]
        star = "*" if "window" in dense else ""
        table.add_row(
            f"{row['gaussians']:,}",
            row["resolution"],
            f"{row['mean_radius_px']:.1f}",
            f"{row['pairs'] / 1e6:.2f}M",
            f"{sparse['fwd_s']:.3f}",
            f"{sparse['fwd_bwd_s']:.3f}",
            f"{sparse['peak_mb']:.0f}",
            f"{dense['fwd_s']:.2f}{star}",
            f"{dense['fwd_bwd_s']:.2f}{star}",
            f"{dense['peak_mb']:.0f}{star}",
            dense.get("window", "full") + (f" ({dense['measured_pixels']} px)" if star else ""),
            f"{row['speedup_fwd']:.0f}x",
            f"{row['speedup_fwd_bwd']:.0f}x",
        )
    return table


def report(cfg: BenchConfig) -> None:
    """Run the benchmark, print its table and optionally save the results as JSON."""
    if cfg.quick:
        cfg = dataclasses.replace(cfg, sizes=(10_000,), resolutions=("220x146",), repeats=1)
    load_start = os.getloadavg()
    rows = run_cases(cfg)
    load_end = os.getloadavg()
    console = Console(width=200)
    console.print(render_table(rows, cfg))
    console.print(
        f"load average (1/5/15 min) at start {load_start[0]:.2f}/{load_start[1]:.2f}/{load_start[2]:.2f}, "
        f"at end {load_end[0]:.2f}/{load_end[1]:.2f}/{load_end[2]:.2f} on {os.cpu_count()} CPUs"
    )
    if cfg.out_json is not None:
        payload = {
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()},
            "torch": torch.__version__,
            "cpu_count": os.cpu_count(),
            "load_average_start": load_start,
            "load_average_end": load_end,
            "results": rows,
        }
        cfg.out_json.write_text(json.dumps(payload, indent=2))


def main() -> None:
    """Console script ``naka-gs-bench-raster``: the sparse-vs-dense rasterizer benchmark."""
    report(tyro.cli(BenchConfig))


if __name__ == "__main__":
    main()
