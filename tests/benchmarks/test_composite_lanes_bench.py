"""python -m benchmarks.composite_lanes: both kernel pairs timed and compared on a tiny synthetic scene."""

from __future__ import annotations

import pytest
from rich.console import Console

import benchmarks.composite_lanes as bench
import naka_gs_plugin.model.rasterize_cpu_fast as cpu_fast


def test_both_kernel_pairs_are_timed_and_agree(monkeypatch):
    console = Console(width=300, record=True)
    monkeypatch.setattr(bench, "CONSOLE", console)
    default_min_run = cpu_fast.RGB32_MIN_RUN
    bench.entrypoint(["--gaussians", "400", "--widths", "64", "--repeats", "1"])
    assert cpu_fast.RGB32_MIN_RUN == default_min_run  # restored after forcing each pair
    row = next(line for line in console.export_text().splitlines() if "64x48" in line)
    cells = [c.strip() for c in row.split("│") if c.strip()]
    assert cells[1:3] == ["1", "400"]
    colour_diff, grad_diff = float(cells[7]), float(cells[8])
    assert colour_diff <= 1e-5 and grad_diff <= 1e-3  # the same render to float32 rounding
    assert cells[9] == ("8-wide" if float(cells[3]) >= default_min_run else "generic")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--repeats", "0"], "--repeats, --views and --threads must be >= 1"),
        (["--config", "nowhere.yml"], "no such config"),
    ],
)
def test_bad_arguments_are_refused(args, message):
    with pytest.raises(SystemExit, match=message):
        bench.entrypoint(args)
