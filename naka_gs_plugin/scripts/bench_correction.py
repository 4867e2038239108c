"""``naka-gs-bench-correction``: time, peak memory and quality of every correction inference mode.

What is measured, and how, is described in :mod:`naka_gs_plugin.bench.correction_bench`.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import tyro

from naka_gs_plugin.bench.correction_bench import BORDER, DATA, low_and_naka, net_for, run_child, set_means
from naka_gs_plugin.bench.harness import run_isolated
from naka_gs_plugin.bench.machine import describe_cpu
from naka_gs_plugin.enhance.correction import DEFAULT_MODE, MODES


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
    """Console script ``naka-gs-bench-correction``."""
    tyro.cli(BenchCorrection, args=args).main()


if __name__ == "__main__":
    entrypoint()
