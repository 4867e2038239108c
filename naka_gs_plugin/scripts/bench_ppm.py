"""``naka-gs-bench-ppm``: PPM runtime, ours against a plain re-implementation of the authors' PPM.

The clouds and the reference are described in :mod:`naka_gs_plugin.bench.ppm_bench`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import tyro

from naka_gs_plugin.bench.ppm_bench import compare


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
    """Console script ``naka-gs-bench-ppm``."""
    tyro.cli(BenchPpm, args=args).main()


if __name__ == "__main__":
    entrypoint()
