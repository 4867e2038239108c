"""Benchmark the CPU rasterizers: compiled cpu-fast vs our torch path vs the dense reference.

Every case (method x Gaussians x resolution x threads) runs in a fresh spawned process, so each
one's peak memory is its own (:mod:`benchmarks.harness`): "peak MB" is the kernel's peak
resident set size of the process (``VmHWM``, reset just before the first render) minus its
resident size at that moment, i.e. the extra host memory the renders (forward and backward,
including allocator caches) needed at their peak. On CUDA it is
``torch.cuda.max_memory_allocated`` instead. cpu-fast's kernels are compiled or loaded from numba's
disk cache before the clock starts; the compile time is reported separately (a process with an
empty ``NUMBA_CACHE_DIR``, then one loading that cache). Timings are only meaningful on an
otherwise idle machine; the load averages at the start and end are recorded with the results.

Thread scaling: cpu-fast runs with ``--threads`` and with 1 thread (``numba.set_num_threads`` and
``torch.set_num_threads`` together); the torch path and the dense reference with ``--threads``.

The dense reference materialises pixels x Gaussians tensors, so unless that product fits
``--dense-budget`` it is not run on the full image. Its cost is ``t0 + k * pixels``; it is timed on
a 1-pixel image and on a top-left window of the same camera (same intrinsics, smaller image) with
pixels x Gaussians within the budget, and that line is extrapolated to the full image. Such rows
are marked with ``*``; their memory is that of the window.

The scene imitates a trained splatfacto scene: Gaussians spread through the view frustum at depths
2..10 (60 degree horizontal field of view), random orientations, log-normal anisotropic scales
(sigma 0.6 in log space per axis) whose median projects to a 0.6 px standard deviation at the mean
depth at 441 px width, i.e. a mean radius of ~4.7 px after gsplat's 0.3 px^2 blur (sizes grow with
the resolution, as when rendering one scene larger), sigmoid(N(0, 2)) opacities and degree-3 SH
colours. The table reports the mean radius of the visible Gaussians and the number of
Gaussian-pixel pairs with ``alpha >= 1/255`` inside the radius boxes.

Also reported: the viewer's frame time (``NakaGSModel.get_outputs`` under ``torch.no_grad``, eval
mode, so RGB + expected depth as the viewer renders) and a profile of one forward+backward of
cpu-fast split into projection, SH colours, sort+bin, the two kernels and the rest.

Run from the repository root: ``python -m benchmarks.rasterizer --help``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import torch
import tyro
from rich.console import Console
from rich.table import Table

from benchmarks.harness import peak_rss, reset_peak_rss, run_isolated
from benchmarks.machine import describe_cpu

SH_DEGREE = 3
FOV_X_DEG = 60.0
REFERENCE_WIDTH = 441
MEDIAN_SIGMA_PX = 0.6
"""Median projected standard deviation (px) of a Gaussian axis at the mean depth at 441 px width."""
METHODS = ("cpu-fast", "torch", "dense")


@dataclasses.dataclass
class BenchConfig:
    """cpu-fast vs torch vs dense rasterizer: timing (forward, forward+backward), peak memory,
    thread scaling, viewer frame time, cpu-fast compile time and a stage profile."""

    sizes: Tuple[int, ...] = (10_000, 50_000, 100_000, 300_000)
    """Numbers of Gaussians."""
    resolutions: Tuple[str, ...] = ("220x146", "441x293", "882x586")
    """Image sizes as WIDTHxHEIGHT."""
    repeats: int = 3
    """Timed repetitions per case after one warm-up; the median is reported."""
    threads: int = 2
    """Threads (torch intra-op and numba) of the main runs; cpu-fast is also run with 1."""
    dense_budget: int = 20_000_000
    """Largest pixels x Gaussians product the dense reference renders in one go; 0 skips the dense
    reference (its columns show "-")."""
    viewer_resolution: str = "441x293"
    """Image size of the viewer frame-time runs (one per size, cpu-fast and torch)."""
    profile_case: str = "100000@441x293"
    """GAUSSIANS@WIDTHxHEIGHT of the cpu-fast stage profile."""
    device: str = "cpu"
    """Torch device for the torch path and dense reference (cpu-fast is CPU-only), e.g. cuda."""
    quick: bool = False
    """Smoke run: 10k Gaussians at 220x146, one repetition, profile and viewer at that size."""
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


def sync(device: str) -> None:
    """Wait for the GPU's queued work (timings of CUDA renders); nothing on the CPU."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _renderer(method: str):
    if method == "cpu-fast":
        from naka_gs_plugin.model.rasterize_cpu_fast import rasterization, warm_up

        warm_up(torch.float32)
        return rasterization
    if method == "torch":
        from naka_gs_plugin.model.rasterize import rasterization

        return rasterization
    from naka_gs_plugin.model.rasterize_dense import rasterization_dense

    return rasterization_dense


def _set_threads(threads: int) -> None:
    import numba

    # numba first: starting its OpenMP pool resets the shared runtime's (hence PyTorch's) thread count.
    numba.set_num_threads(threads)
    torch.set_num_threads(threads)


def time_fwd_bwd(render, scene: Dict, width: int, height: int, repeats: int, device: str) -> Tuple[float, float]:
    """Median forward and forward+backward seconds of ``repeats`` renders of ``render`` (gsplat's
    ``rasterization`` interface) after one warm-up; the loss: mean squared colour + mean alpha."""
    fwd, total = [], []
    for _ in range(repeats + 1):
        params = {k: v.detach().clone().requires_grad_(k not in ("viewmats", "Ks")) for k, v in scene.items()}
        sync(device)
        t0 = time.perf_counter()
        colors, alphas, _ = render(**params, width=width, height=height, sh_degree=SH_DEGREE)
        sync(device)
        t1 = time.perf_counter()
        (colors.square().mean() + alphas.mean()).backward()
        sync(device)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        total.append(t2 - t0)
        del colors, alphas, params
    return statistics.median(fwd[1:]), statistics.median(total[1:])


def extrapolate(
    one: Tuple[float, float], window: Tuple[float, float], window_pixels: int, pixels: int
) -> Optional[Tuple[float, float]]:
    """(forward, forward+backward) seconds at ``pixels`` on the line through the 1-pixel and the
    window timings, or None when a window is not slower than one pixel (noise, not a cost per pixel:
    extrapolating it hundreds of times over printed negative times)."""
    if any(w <= o for o, w in zip(one, window)):
        return None
    scale = (pixels - 1) / (window_pixels - 1)
    return tuple(o + (w - o) * scale for o, w in zip(one, window))


def _run_case(method: str, n: int, width: int, height: int, threads: int, cfg: BenchConfig) -> Optional[Dict]:
    """One benchmark case, meant to run in a fresh process (its peak memory is its own)."""
    _set_threads(threads)
    device = "cpu" if method == "cpu-fast" else cfg.device
    scene = make_scene(n, width, height, device=device)
    _renderer(method)  # cpu-fast: compile / load the kernels before measuring
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        base = reset_peak_rss()
    result: Dict = {"method": method, "gaussians": n, "width": width, "height": height, "threads": threads}
    if method != "dense" or n * width * height <= cfg.dense_budget:
        result["fwd_s"], result["fwd_bwd_s"] = time_fwd_bwd(
            _renderer(method), scene, width, height, cfg.repeats, device
        )
        result["measured_pixels"] = width * height
    else:
        # Dense cost is t0 + k * pixels: measure a 1-pixel and a budget-sized top-left window of the
        # same camera (same K, smaller image) and extrapolate the line to the full image.
        pixels = max(2, cfg.dense_budget // n)
        win_w = min(width, pixels)
        win_h = max(1, min(height, pixels // win_w))
        one = time_fwd_bwd(_renderer(method), scene, 1, 1, cfg.repeats, device)
        window = time_fwd_bwd(_renderer(method), scene, win_w, win_h, cfg.repeats, device)
        line = extrapolate(one, window, win_w * win_h, width * height)
        if line is None:
            return None  # shown as "-": the window is too small to tell its per-pixel cost from noise
        result["fwd_s"], result["fwd_bwd_s"] = line
        result["measured_pixels"] = win_w * win_h
        result["window"] = f"{win_w}x{win_h}"
    if device.startswith("cuda"):
        result["peak_mb"] = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:
        result["peak_mb"] = (peak_rss() - base) / 2**20
    return result


def _viewer_frame(method: str, n: int, width: int, height: int, threads: int, repeats: int) -> Dict:
    """Median seconds of ``NakaGSModel.get_outputs`` (eval, no grad) for one viewer frame."""
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.data.scene_box import SceneBox

    from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig

    _set_threads(threads)
    _renderer(method)
    scene = make_scene(n, width, height)
    rgb = torch.zeros(n, 3, dtype=torch.uint8)
    box = SceneBox(aabb=torch.tensor([[-10.0, -10, 0], [10, 10, 10]]))
    model = NakaGSModelConfig(sh_degree=SH_DEGREE, rasterizer=method).setup(
        scene_box=box, num_train_data=1, seed_points=(scene["means"], rgb)
    )
    params = model.gauss_params
    params["means"].data.copy_(scene["means"])
    params["quats"].data.copy_(scene["quats"])
    params["scales"].data.copy_(torch.log(scene["scales"]))
    params["opacities"].data.copy_(torch.logit(scene["opacities"])[:, None])
    params["features_dc"].data.copy_(scene["colors"][:, 0])
    params["features_rest"].data.copy_(scene["colors"][:, 1:])
    model.step = 10**6  # full SH degree
    model.eval()
    k = scene["Ks"][0]
    # The scene's camera is the OpenCV identity; nerfstudio poses are OpenGL camera-to-world.
    c2w = torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0]])[None]
    camera = Cameras(camera_to_worlds=c2w, fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], width=width, height=height)
    times = []
    with torch.no_grad():
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            out = model.get_outputs(camera)
            times.append(time.perf_counter() - t0)
    assert out["rgb"].shape == (height, width, 3)
    return {"method": method, "gaussians": n, "frame_s": statistics.median(times[1:])}


def _stage_profile(n: int, width: int, height: int, threads: int, repeats: int) -> Dict[str, float]:
    """Median wall seconds per stage of one cpu-fast forward+backward (same loss as the table)."""
    from naka_gs_plugin.model.project_cpu_fast import project_gaussians, sh_colors
    from naka_gs_plugin.model.rasterize_cpu_fast import profile_stages

    _set_threads(threads)
    render = _renderer("cpu-fast")
    scene = make_scene(n, width, height)
    runs: List[Dict[str, float]] = []
    for _ in range(repeats + 1):
        p = {k: v.detach().clone().requires_grad_(k not in ("viewmats", "Ks")) for k, v in scene.items()}
        t0 = time.perf_counter()
        proj = project_gaussians(p["means"], p["quats"], p["scales"], p["viewmats"], p["Ks"], width, height)
        (proj.means2d.sum() + proj.conics.sum() + proj.depths.sum()).backward()
        t1 = time.perf_counter()
        sh_colors(p["means"], p["colors"], p["viewmats"], SH_DEGREE).sum().backward()
        t2 = time.perf_counter()
        p = {k: v.detach().clone().requires_grad_(k not in ("viewmats", "Ks")) for k, v in scene.items()}
        with profile_stages() as stages:
            t3 = time.perf_counter()
            colors, alphas, _ = render(**p, width=width, height=height, sh_degree=SH_DEGREE)
            (colors.square().mean() + alphas.mean()).backward()
            total = time.perf_counter() - t3
        row = {"projection f+b (numba)": t1 - t0, "SH colours f+b (numba)": t2 - t1, **stages}
        # Projection and SH are timed in their own calls, so on a busy machine this can go negative.
        row["rest: total - rows above"] = total - sum(row.values())
        row["total f+b"] = total
        runs.append(row)
    return {key: statistics.median(r[key] for r in runs[1:]) for key in runs[0]}


def _compile_seconds(cache_dir: str) -> float:
    """Seconds to get cpu-fast's float32 kernels ready in a fresh process using ``cache_dir``."""
    os.environ["NUMBA_CACHE_DIR"] = cache_dir
    from naka_gs_plugin.model.rasterize_cpu_fast import warm_up

    return warm_up(torch.float32)


def run_cases(cfg: BenchConfig) -> Dict:
    """Run every case, each in a fresh spawned process."""
    console = Console(stderr=True)
    out: Dict = {}
    with tempfile.TemporaryDirectory() as cache_dir:
        console.log("cpu-fast kernels: cold compile, then cache load ...")
        out["compile_s"] = run_isolated(_compile_seconds, cache_dir)
        out["cache_load_s"] = run_isolated(_compile_seconds, cache_dir)
    rows = []
    for res in cfg.resolutions:
        width, height = (int(v) for v in res.lower().split("x"))
        for n in cfg.sizes:
            radius, pairs = scene_stats(make_scene(n, width, height), width, height)
            row = {"gaussians": n, "resolution": res, "mean_radius_px": radius, "pairs": pairs}
            for method in METHODS:
                if method == "dense" and cfg.dense_budget == 0:
                    row[method] = None
                    continue
                console.log(f"{method} {n} Gaussians at {res}, {cfg.threads} threads ...")
                row[method] = run_isolated(_run_case, method, n, width, height, cfg.threads, cfg)
            if cfg.threads != 1:
                console.log(f"cpu-fast {n} Gaussians at {res}, 1 thread ...")
                row["cpu-fast-1"] = run_isolated(_run_case, "cpu-fast", n, width, height, 1, cfg)
            rows.append(row)
    out["rows"] = rows
    width, height = (int(v) for v in cfg.viewer_resolution.lower().split("x"))
    out["viewer"] = []
    for n in cfg.sizes:
        for method in ("cpu-fast", "torch"):
            console.log(f"viewer frame: {method} {n} Gaussians at {cfg.viewer_resolution} ...")
            args = (method, n, width, height, cfg.threads, cfg.repeats)
            out["viewer"].append(run_isolated(_viewer_frame, *args))
    n_text, res = cfg.profile_case.split("@")
    width, height = (int(v) for v in res.lower().split("x"))
    console.log(f"cpu-fast stage profile at {cfg.profile_case} ...")
    profile_args = (int(n_text), width, height, cfg.threads, cfg.repeats)
    out["profile"] = run_isolated(_stage_profile, *profile_args)
    return out


def render_table(rows: List[Dict], cfg: BenchConfig) -> Table:
    table = Table(
        title=f"Rasterizer benchmark (fwd+bwd and fwd seconds, {cfg.threads} threads unless stated, "
        f"median of {cfg.repeats})",
        caption=(
            "MB: peak RSS (VmHWM) minus RSS before rendering, per case in a fresh process. "
            "dense*: extrapolated linearly in pixels from a 1-pixel image and a window of the same camera "
            "(pixels x Gaussians <= --dense-budget); its MB is that of the window; '-': skipped (budget 0) or "
            "the window was not slower than one pixel (too small to measure). "
            "x torch / x dense: forward+backward time of that method over cpu-fast's."
        ),
    )
    columns = ["Gaussians", "image", "mean r px", "pairs"]
    columns += ["cpu-fast f+b", "cpu-fast fwd", "cpu-fast f+b 1 thr", "thread scaling", "cpu-fast MB"]
    columns += ["torch f+b", "torch fwd", "torch MB", "dense f+b", "dense fwd", "dense MB"]
    columns += ["x torch", "x dense"]
    for col in columns:
        table.add_column(col, justify="right")
    for row in rows:
        fast, ref, dense = row["cpu-fast"], row["torch"], row["dense"]
        one = row.get("cpu-fast-1")
        star = "*" if dense is not None and "window" in dense else ""
        table.add_row(
            f"{row['gaussians']:,}",
            row["resolution"],
            f"{row['mean_radius_px']:.1f}",
            f"{row['pairs'] / 1e6:.2f}M",
            f"{fast['fwd_bwd_s']:.3f}",
            f"{fast['fwd_s']:.3f}",
            f"{one['fwd_bwd_s']:.3f}" if one else "-",
            f"{one['fwd_bwd_s'] / fast['fwd_bwd_s']:.2f}x" if one else "-",
            f"{fast['peak_mb']:.0f}",
            f"{ref['fwd_bwd_s']:.3f}",
            f"{ref['fwd_s']:.3f}",
            f"{ref['peak_mb']:.0f}",
            f"{dense['fwd_bwd_s']:.2f}{star}" if dense else "-",
            f"{dense['fwd_s']:.2f}{star}" if dense else "-",
            f"{dense['peak_mb']:.0f}{star}" if dense else "-",
            f"{ref['fwd_bwd_s'] / fast['fwd_bwd_s']:.1f}x",
            f"{dense['fwd_bwd_s'] / fast['fwd_bwd_s']:.0f}x" if dense else "-",
        )
    return table


def report(cfg: BenchConfig) -> None:
    """Run the benchmark, print its tables and optionally save the results as JSON."""
    if cfg.quick:
        cfg = dataclasses.replace(
            cfg, sizes=(10_000,), resolutions=("220x146",), repeats=1, profile_case="10000@220x146"
        )
    load_start = os.getloadavg()
    results = run_cases(cfg)
    load_end = os.getloadavg()
    console = Console(width=220)
    console.print(render_table(results["rows"], cfg))
    viewer = Table(title=f"Viewer frame time at {cfg.viewer_resolution} (get_outputs, no grad, RGB+ED)")
    for col in ("Gaussians", "cpu-fast s", "torch s", "x torch"):
        viewer.add_column(col, justify="right")
    frames = {(v["method"], v["gaussians"]): v["frame_s"] for v in results["viewer"]}
    for n in cfg.sizes:
        fast, ref = frames[("cpu-fast", n)], frames[("torch", n)]
        viewer.add_row(f"{n:,}", f"{fast:.3f}", f"{ref:.3f}", f"{ref / fast:.1f}x")
    console.print(viewer)
    profile = Table(title=f"cpu-fast forward+backward profile at {cfg.profile_case} ({cfg.threads} threads)")
    profile.add_column("stage")
    profile.add_column("s", justify="right")
    profile.add_column("share", justify="right")
    total = results["profile"]["total f+b"]
    for stage, seconds in results["profile"].items():
        profile.add_row(stage, f"{seconds:.3f}", f"{100 * seconds / total:.0f}%")
    console.print(profile)
    console.print(
        f"cpu-fast float32 kernels: {results['compile_s']:.1f} s to compile (empty NUMBA_CACHE_DIR), "
        f"{results['cache_load_s']:.1f} s to load from numba's disk cache"
    )
    console.print(
        f"load average (1/5/15 min) at start {load_start[0]:.2f}/{load_start[1]:.2f}/{load_start[2]:.2f}, "
        f"at end {load_end[0]:.2f}/{load_end[1]:.2f}/{load_end[2]:.2f} on {os.cpu_count()} CPUs"
    )
    console.print(describe_cpu(), markup=False)
    if cfg.out_json is not None:
        payload = {
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()},
            "torch": torch.__version__,
            "cpu_count": os.cpu_count(),
            "cpu": describe_cpu(),
            "load_average_start": load_start,
            "load_average_end": load_end,
            **results,
        }
        cfg.out_json.write_text(json.dumps(payload, indent=2))


@dataclass
class BenchRaster(BenchConfig):
    """cpu-fast vs torch vs dense rasterizer: timing (forward, forward+backward), peak memory,
    thread scaling, viewer frame time, cpu-fast compile time and a stage profile."""

    def main(self) -> None:
        if self.dense_budget < 0:
            raise SystemExit(
                f"python -m benchmarks.rasterizer: --dense-budget must be >= 0 (0 skips the dense reference), got {self.dense_budget}"
            )
        report(self)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.rasterizer``."""
    tyro.cli(BenchRaster, args=args).main()


if __name__ == "__main__":
    entrypoint()
