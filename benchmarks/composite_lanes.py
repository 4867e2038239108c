"""cpu-fast's float32 RGB compositing kernels (8 pixels a vector) against its generic ones, per image size.

Training renders (float32 RGB) take ``_forward_kernel_rgb32`` / ``_backward_kernel_rgb32`` when their row
spans average at least ``RGB32_MIN_RUN`` pixels per (list entry, tile row), since narrower spans leave
most lanes idle. Per image size this prints that average, the forward+backward wall of the whole cpu-fast
``rasterization`` with each kernel pair forced (alternated in one process, median of ``--repeats``), their
largest differences, and which pair the default picks: the measurement behind ``RGB32_MIN_RUN`` on the CPU
it runs on (stated first). The scene: a trained run's Gaussians and training cameras at 1/4, 1/2 and full
size (``--config``, its ``config.yml``), or by default the synthetic trained-scene-like Gaussians of
``python -m benchmarks.rasterizer`` at several widths. Run from the repository root on an idle machine:
``python -m benchmarks.composite_lanes --help``.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numba
import torch
import tyro
from rich.console import Console
from rich.table import Table

import naka_gs_plugin.model.rasterize_cpu_fast as cpu_fast
from benchmarks.machine import describe_cpu
from benchmarks.rasterizer import SH_DEGREE, make_scene

CONSOLE = Console(width=140)
PARAMS = ("means", "quats", "scales", "opacities", "colors")
KERNELS = {"generic": math.inf, "8-wide": 0.0}
"""Kernel pair -> the ``RGB32_MIN_RUN`` that forces it."""


def synthetic_renders(gaussians: int, widths: Sequence[int]) -> List[List[Dict]]:
    """Per width (4:3), one render of :func:`benchmarks.rasterizer.make_scene`'s scene."""
    renders = []
    for width in widths:
        height = round(width * 3 / 4)
        scene = make_scene(gaussians, width, height)
        renders.append([dict(scene, width=width, height=height, sh_degree=SH_DEGREE)])
    return renders


def trained_renders(config: Path, scales: Sequence[int], views: int) -> List[List[Dict]]:
    """Per downscale factor, the cpu-fast ``rasterization`` arguments of ``views`` training views of a
    trained run, as its model renders them (RGB, the training case)."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config, test_mode="val")
    model = pipeline.model
    cameras = pipeline.datamanager.train_dataset.cameras
    picked = list(range(0, len(cameras), max(1, len(cameras) // views)))[:views]
    calls: List[Dict] = []
    shipped = cpu_fast.rasterization

    def record(**kwargs):
        calls.append({**kwargs, "render_mode": "RGB"})
        return shipped(**kwargs)

    renders = []
    cpu_fast.rasterization = record
    try:
        with torch.no_grad():
            for scale in scales:
                calls.clear()
                for i in picked:
                    camera = cameras[i : i + 1]
                    camera.rescale_output_resolution(1.0 / scale)
                    model.get_outputs(camera)
                renders.append(list(calls))
    finally:
        cpu_fast.rasterization = shipped
    return renders


def forward_backward(
    renders: List[Dict], weights: List[torch.Tensor]
) -> List[Tuple[torch.Tensor, Dict[str, torch.Tensor]]]:
    """Render each view and backpropagate ``sum(weights * colour)``; each view's colours and gradients."""
    results = []
    for kwargs, weight in zip(renders, weights):
        inputs = {k: _leaf(kwargs[k]) for k in PARAMS}
        colors, _, _ = cpu_fast.rasterization(**{**kwargs, **inputs})
        (colors * weight).sum().backward()
        results.append((colors.detach(), {k: _grad(inputs[k]) for k in PARAMS}))
    return results


def _leaf(value: Union[torch.Tensor, Tuple[torch.Tensor, ...]]) -> Union[torch.Tensor, Tuple[torch.Tensor, ...]]:
    """A leaf copy; of each part for the model's SH colours ``(features_dc, features_rest)``."""
    if isinstance(value, tuple):
        return tuple(part.detach().clone().requires_grad_() for part in value)
    return value.detach().clone().requires_grad_()


def _grad(value: Union[torch.Tensor, Tuple[torch.Tensor, ...]]) -> torch.Tensor:
    """The leaf's gradient; the parts' side by side, one row per Gaussian, for a tuple."""
    if isinstance(value, tuple):
        return torch.cat([part.grad.reshape(part.shape[0], -1) for part in value], 1)
    return value.grad


def span_width(renders: List[Dict]) -> Tuple[float, bool]:
    """Span pixels per (list entry, tile row) over the renders, and whether the default takes the 8-wide pair."""
    seen = []
    choose = cpu_fast._spans_suit_lanes

    def spy(tile_start, vis_start, slot_y):
        seen.append(cpu_fast.span_counts(vis_start, slot_y))
        return choose(tile_start, vis_start, slot_y)

    cpu_fast._spans_suit_lanes = spy
    try:
        with torch.no_grad():
            for kwargs in renders:
                cpu_fast.rasterization(**kwargs)
    finally:
        cpu_fast._spans_suit_lanes = choose
    pixels, rows = sum(p for p, _ in seen), sum(r for _, r in seen)
    width = pixels / max(rows, 1)
    return width, width >= cpu_fast.RGB32_MIN_RUN


@dataclass
class BenchCompositeLanes:
    """cpu-fast's 8-wide float32 RGB compositing kernels against its generic ones, per image size."""

    config: Optional[Path] = None
    """A trained run's config.yml (its Gaussians and training cameras); default: a synthetic scene."""
    scales: Tuple[int, ...] = (4, 2, 1)
    """With --config: downscale factors of the training cameras (splatfacto's resolution schedule)."""
    views: int = 5
    """With --config: training views rendered per size."""
    gaussians: int = 30_000
    """Without --config: Gaussians of the synthetic scene."""
    widths: Tuple[int, ...] = (125, 250, 500)
    """Without --config: image widths (4:3) of the synthetic scene."""
    repeats: int = 7
    """Timed rounds (each kernel pair once per round, the order alternating); medians are reported."""
    threads: int = 1
    """numba and PyTorch threads."""

    def main(self) -> None:
        if self.repeats < 1 or self.views < 1 or self.threads < 1:
            raise SystemExit("python -m benchmarks.composite_lanes: --repeats, --views and --threads must be >= 1")
        if self.config is not None and not self.config.is_file():
            raise SystemExit(f"python -m benchmarks.composite_lanes: no such config file {self.config}")
        numba.set_num_threads(self.threads)  # before torch's: numba's pool start resets the shared runtime's count
        torch.set_num_threads(self.threads)
        CONSOLE.print(describe_cpu())
        cpu_fast.warm_up(torch.float32)
        if self.config is not None:
            sizes = trained_renders(self.config, self.scales, self.views)
        else:
            sizes = synthetic_renders(self.gaussians, self.widths)
        table = Table(title=f"cpu-fast compositing, float32 RGB, forward+backward, {self.threads} thread(s)")
        for column in (
            "size", "views", "Gaussians", "px per entry row", "generic ms", "8-wide ms", "8-wide / generic",
            "max |colour diff|", "max grad diff (rel.)", "default",
        ):  # fmt: skip
            table.add_column(column, justify="right")
        for renders in sizes:
            gen = torch.Generator().manual_seed(0)
            weights = [torch.randn(1, r["height"], r["width"], 3, generator=gen) for r in renders]
            width, lanes = span_width(renders)
            results, seconds = {}, {name: [] for name in KERNELS}
            for repeat in range(self.repeats + 1):  # the first round warms up and is not timed
                order = list(KERNELS.items())
                for name, min_run in order if repeat % 2 == 0 else order[::-1]:
                    cpu_fast.RGB32_MIN_RUN, kept = min_run, cpu_fast.RGB32_MIN_RUN
                    try:
                        started = time.perf_counter()
                        results[name] = forward_backward(renders, weights)
                        if repeat:
                            seconds[name].append(time.perf_counter() - started)
                    finally:
                        cpu_fast.RGB32_MIN_RUN = kept
            colour_diff = grad_diff = 0.0
            for (c_gen, g_gen), (c_lanes, g_lanes) in zip(results["generic"], results["8-wide"]):
                colour_diff = max(colour_diff, float((c_lanes - c_gen).abs().max()))
                for k in PARAMS:  # relative to the parameter's largest gradient
                    scale = g_gen[k].abs().max().clamp(min=1e-30)
                    grad_diff = max(grad_diff, float((g_lanes[k] - g_gen[k]).abs().max() / scale))
            generic, wide = (1000 * statistics.median(seconds[name]) for name in ("generic", "8-wide"))
            table.add_row(
                f"{renders[0]['width']}x{renders[0]['height']}",
                str(len(renders)),
                f"{renders[0]['means'].shape[0]:,}",
                f"{width:.2f}",
                f"{generic:.1f}",
                f"{wide:.1f}",
                f"{wide / generic:.2f}x",
                f"{colour_diff:.1e}",
                f"{grad_diff:.1e}",
                "8-wide" if lanes else "generic",
            )
        CONSOLE.print(table)
        CONSOLE.print(f"RGB32_MIN_RUN = {cpu_fast.RGB32_MIN_RUN} span pixels per entry row")


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.composite_lanes``."""
    tyro.cli(BenchCompositeLanes, args=args).main()


if __name__ == "__main__":
    entrypoint()
