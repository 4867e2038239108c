"""``naka-gs-bench-raster``: the CPU rasterizers (cpu-fast, torch, dense) timed, measured and profiled.

The cases and the isolation of each run are described in :mod:`naka_gs_plugin.bench.rasterizer_bench`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import tyro

from naka_gs_plugin.bench.rasterizer_bench import BenchConfig, report


@dataclass
class BenchRaster(BenchConfig):
    """cpu-fast vs torch vs dense rasterizer: timing (forward, forward+backward), peak memory,
    thread scaling, viewer frame time, cpu-fast compile time and a stage profile."""

    def main(self) -> None:
        if self.dense_budget < 0:
            raise SystemExit(
                f"naka-gs-bench-raster: --dense-budget must be >= 0 (0 skips the dense reference), got {self.dense_budget}"
            )
        report(self)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-bench-raster``."""
    tyro.cli(BenchRaster, args=args).main()


if __name__ == "__main__":
    entrypoint()
