"""Correction-network inference benchmark: time, peak memory and quality of every inference mode.

Each mode runs in a fresh process (so its peak RSS is its own: :mod:`benchmarks.harness`)
on one image, default a 1764x1172 RealX3D view (``--resolution-scale 0.5``: 882x586): wall and CPU seconds of
``CorrectionRunner`` on the (low, Naka) pair after a small warm-up, peak RSS of the whole process, and
the difference of its output to the ``exact`` mode (max and mean abs, and max abs at least 16 px
inside the borders). ``exact`` -- the authors' architecture as a plain float32 NCHW forward -- is
always run in the same invocation and is the reference of every ratio; ``auto`` is timed as the mode
it resolves to on this machine.
Tiled modes also report their difference to the untiled forward that replays the same recorded
statistics (the tiling error alone). Modes in ``--quality-modes`` are scored against ground truth on
the LOM test views and LOL eval15 (PSNR on [0,1], SSIM with kornia's 11x11 window), and the
deltas to ``exact`` are printed (tiled modes through their untiled equivalent with the same
recorded statistics). The first line printed describes the CPU (:func:`describe_cpu`).

Run from the repository root: ``python -m benchmarks.correction_speed --help``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import tyro

from benchmarks.harness import peak_rss, run_isolated
from benchmarks.machine import describe_cpu
from naka_gs_plugin.enhance.correction import DEFAULT_MODE, MODES

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BORDER = 16
"""Pixels excluded at each image border for the interior difference."""


def net_for(weights: str):
    import torch

    from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS, load_correction
    from naka_gs_plugin.enhance.correction_net import ChromaGuided

    if weights == "random":
        torch.manual_seed(0)
        return ChromaGuided().eval()
    return load_correction(DEFAULT_WEIGHTS if weights == "default" else weights)


def low_and_naka(path: Path):
    """(low, naka) as float32 ``[1, 3, H, W]`` sRGB [0, 1] (Naka: reference parameters, per image)."""
    import torch

    from naka_gs_plugin.data.images import read_rgb
    from naka_gs_plugin.enhance.naka import naka_enhance

    low = torch.from_numpy(read_rgb(path))
    return low.permute(2, 0, 1)[None].contiguous(), naka_enhance(low).permute(2, 0, 1)[None].contiguous()


def quality_pairs() -> List[Tuple[str, Path, Path]]:
    """(set, low, gt) for the LOM test views (``transforms_test.json``) and LOL eval15."""
    pairs = []
    for scene in sorted((DATA / "lom").glob("*/transforms_test.json")):
        for frame in json.loads(scene.read_text(encoding="utf-8-sig"))["frames"]:
            gt = scene.parent / frame["file_path"]
            pairs.append(("lom", scene.parent / "low" / gt.name, gt))
    for gt in sorted((DATA / "lol" / "eval" / "high").glob("*")):
        pairs.append(("lol", DATA / "lol" / "eval" / "low" / gt.name, gt))
    return pairs


def run_child(
    mode_name: str,
    image: Path,
    weights: str,
    out_dir: Path,
    timing: bool,
    quality: bool,
    threads: int,
    repeats: int,
    resolution_scale: float = 1.0,
) -> dict:
    """Measure one mode in this (fresh) process; writes ``<mode>.npy`` (the output) to ``out_dir``."""
    import kornia
    import numba
    import torch

    # numba first: starting its OpenMP pool resets the shared runtime's (hence PyTorch's) thread count.
    numba.set_num_threads(threads)
    torch.set_num_threads(threads)

    from naka_gs_plugin.enhance.correction import CorrectionRunner, resolve_mode
    from naka_gs_plugin.enhance.correction_net import apply_maps
    from naka_gs_plugin.metrics import psnr

    torch.set_grad_enabled(False)
    net = net_for(weights)
    runner = CorrectionRunner(net, mode_name)
    result: dict = {"mode": mode_name, "resolved": resolve_mode(mode_name)}
    if timing:
        low, naka = low_and_naka(image)
        if resolution_scale != 1.0:
            low, naka = (
                torch.nn.functional.interpolate(t, scale_factor=resolution_scale, mode="area") for t in (low, naka)
            )
        runner(low[..., :64, :64], naka[..., :64, :64])  # warm-up (oneDNN primitive creation)
        rss_before = peak_rss() / 1e9
        walls, cpus = [], []
        for _ in range(repeats):
            cpu, wall = time.process_time(), time.perf_counter()
            out = runner(low, naka)["enhanced"]
            walls.append(time.perf_counter() - wall)
            cpus.append(time.process_time() - cpu)
        result.update(
            seconds=float(np.median(walls)),
            cpu_seconds=float(np.median(cpus)),
            threads=threads,
            peak_gb=peak_rss() / 1e9,
            rss_before_gb=rss_before,
            load_average=os.getloadavg()[0],
            size=list(low.shape[-2:]),
        )
        np.save(out_dir / f"{mode_name}.npy", out[0].numpy())
        if runner.mode.tile and runner.mode.stats_scale != 1.0:
            # The tiling error alone: the untiled forward replaying the same (approximate) statistics.
            # (With stats_scale 1 those are the exact statistics: the difference to exact says it.)
            mul, add = runner.predict_maps_with_stats(low, naka, runner.record_stats(low, naka))
            same = apply_maps(naka, mul, add, net.config.lf_kernel, net.config.lf_sigma)
            result["tiling_max_abs_interior"] = float((out - same).abs()[..., BORDER:-BORDER, BORDER:-BORDER].max())
    if quality:
        torch.set_num_threads(1)  # scores only: one thread wastes no CPU spinning on a shared machine
        scores = []
        for name, low_path, gt_path in quality_pairs():
            q_low, q_naka = low_and_naka(low_path)
            gt = low_and_naka(gt_path)[0]
            if runner.mode.tile:
                # Tiles equal the untiled forward with the same recorded statistics (the timing pass
                # measures that at full size); on these small images tiling would only cost time.
                mul, add = runner.predict_maps_with_stats(q_low, q_naka, runner.record_stats(q_low, q_naka))
                pred = apply_maps(q_naka, mul, add, net.config.lf_kernel, net.config.lf_sigma)
            else:
                pred = runner(q_low, q_naka)["enhanced"]
            ssim = float(kornia.metrics.ssim(pred, gt, 11).mean())
            scores.append({"set": name, "image": str(gt_path), "psnr": psnr(pred, gt), "ssim": ssim})
        result["quality"] = scores
    return result


def set_means(scores: Sequence[dict], name: str) -> Tuple[float, float]:
    sel = [s for s in scores if s["set"] == name]
    return float(np.mean([s["psnr"] for s in sel])), float(np.mean([s["ssim"] for s in sel]))


@dataclass
class BenchCorrection:
    """Time and peak memory per image for each correction inference mode (fresh process each)."""

    image: Path = DATA / "realx3d" / "BlueHawaii" / "train" / "0001.JPG"
    """Low-light test image (default: a 1764x1172 RealX3D view)."""
    weights: str = "default"
    """``default`` (shipped), a checkpoint path, or ``random`` (seeded random init: timing only)."""
    modes: Tuple[str, ...] = ("auto",) + tuple(MODES)
    """Modes timed (with ``exact``, the reference of every ratio and difference; empty: none)."""
    resolution_scale: float = 1.0
    """Resize the timed image by this factor first (area filter): 0.5 times a RealX3D view at 882x586."""
    quality_modes: Tuple[str, ...] = tuple(MODES)
    """Modes scored on the LOM test views and LOL eval15 against ground truth (empty: none)."""
    threads: int = 2
    """Threads (PyTorch intra-op and numba) of the timed runs."""
    repeats: int = 1
    """Timed runs per mode after the warm-up; the median wall and CPU seconds are reported."""
    json_out: Optional[Path] = None
    """Write all results here as JSON."""
    sheet: Optional[Path] = None
    """Also write a PNG sheet (rows: low, Naka, corrected in ``sheet_mode``) of ``sheet_views``."""
    sheet_views: Tuple[Path, ...] = tuple(
        DATA / "realx3d" / scene / "train" / "0001.JPG" for scene in ("BlueHawaii", "Cupcake", "Laboratory", "Popcorn")
    )
    sheet_mode: str = DEFAULT_MODE
    sheet_width: int = 440
    """Width of each tile of the sheet, pixels."""

    def write_sheet(self) -> Path:
        """Low / Naka / corrected rows for ``sheet_views`` (each view downscaled to ``sheet_width``)."""
        from PIL import Image

        from naka_gs_plugin.enhance.correction import CorrectionRunner
        from naka_gs_plugin.sheet import contact_sheet

        runner = CorrectionRunner(net_for(self.weights), self.sheet_mode)
        cols = []
        for view in self.sheet_views:
            low, naka = low_and_naka(view)
            out = runner(low, naka)["enhanced"]
            cols.append([t[0].permute(1, 2, 0).numpy() for t in (low, naka, out)])
        rows = [[c[i] for c in cols] for i in range(3)]
        self.sheet.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(contact_sheet(rows, max_width=self.sheet_width)).save(self.sheet)
        print(f"wrote {self.sheet} (rows: low, Naka, corrected [{self.sheet_mode}])")
        return self.sheet

    def main(self) -> List[dict]:
        if self.threads < 1 or self.repeats < 1:
            raise ValueError(f"--threads and --repeats must be >= 1, got {self.threads} and {self.repeats}")
        if not 0 < self.resolution_scale <= 1:
            raise ValueError(f"--resolution-scale must be in (0, 1], got {self.resolution_scale}")
        unknown = [m for m in self.modes + self.quality_modes if m != "auto" and m not in MODES]
        if unknown:
            raise ValueError(f"unknown mode(s) {unknown} in --modes/--quality-modes; choose auto or {sorted(MODES)}")
        print(describe_cpu(), flush=True)
        if self.sheet:
            self.write_sheet()
        if not (self.modes or self.quality_modes):  # ``--modes --quality-modes``: the sheet only
            return []
        timed, scored = set(self.modes), set(self.quality_modes)
        for chosen in (timed, scored):
            if chosen:  # exact is the reference of every difference
                chosen.add("exact")
        order = ["exact"] + [m for m in dict.fromkeys(self.modes + self.quality_modes) if m != "exact"]
        results = []
        with tempfile.TemporaryDirectory() as tmp:
            for mode in order:
                args = (mode, self.image, self.weights, Path(tmp), mode in timed, mode in scored)
                r = run_isolated(run_child, *args, self.threads, self.repeats, self.resolution_scale)
                if mode in timed:
                    ref = np.load(Path(tmp) / "exact.npy")
                    diff = np.abs(np.load(Path(tmp) / f"{mode}.npy") - ref)
                    r.update(
                        max_abs=float(diff.max()),
                        mean_abs=float(diff.mean()),
                        max_abs_interior=float(diff[..., BORDER:-BORDER, BORDER:-BORDER].max()),
                    )
                results.append(r)
                self._print(r, results[0])
        if self.json_out:
            self.json_out.parent.mkdir(parents=True, exist_ok=True)
            self.json_out.write_text(json.dumps(results, indent=1))
        return results

    @staticmethod
    def _print(r: dict, exact: dict) -> None:
        name = r["mode"] if r["mode"] == r["resolved"] else f"{r['mode']} ({r['resolved']})"
        line = f"{name:>13}:"
        if "seconds" in r:
            h, w = r["size"]
            line += (
                f" {w}x{h} {r['seconds']:6.2f} s wall ({exact['seconds'] / r['seconds']:4.2f}x exact), "
                f"{r['cpu_seconds']:6.2f} s CPU ({exact['cpu_seconds'] / r['cpu_seconds']:4.2f}x); "
                f"peak RSS {r['peak_gb']:.2f} GB ({r['peak_gb'] / exact['peak_gb']:.2f}x exact); "
                f"vs exact max {r['max_abs']:.2e} (interior {r['max_abs_interior']:.2e}) mean {r['mean_abs']:.2e}; "
                f"load {r['load_average']:.1f}"
            )
        if "tiling_max_abs_interior" in r:
            line += f"; tiled vs untiled same stats {r['tiling_max_abs_interior']:.2e}"
        if "quality" in r:
            for name in ("lom", "lol"):
                p, s = set_means(r["quality"], name)
                p0, s0 = set_means(exact["quality"], name)
                line += f"; {name} PSNR {p:.3f} ({p - p0:+.3f}) SSIM {s:.4f} ({s - s0:+.4f})"
        print(line, flush=True)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.correction_speed``."""
    tyro.cli(BenchCorrection, args=args).main()


if __name__ == "__main__":
    entrypoint()
