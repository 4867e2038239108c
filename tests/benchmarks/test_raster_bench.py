"""python -m benchmarks.rasterizer's handling of the dense reference budget (no timing runs here)."""

from __future__ import annotations

import pytest
from rich.console import Console

import benchmarks.rasterizer as bench
from benchmarks.rasterizer import entrypoint


def _case(fwd_bwd: float, **extra) -> dict:
    return {"fwd_s": fwd_bwd / 3, "fwd_bwd_s": fwd_bwd, "peak_mb": 10.0, **extra}


def _table_text(rows, cfg) -> str:
    console = Console(width=400, record=True)
    console.print(bench.render_table(rows, cfg))
    return console.export_text()


def test_zero_dense_budget_skips_the_dense_reference():
    row = {"gaussians": 1000, "resolution": "20x10", "mean_radius_px": 2.0, "pairs": 5000}
    row.update({"cpu-fast": _case(0.1), "torch": _case(0.5), "dense": None, "cpu-fast-1": _case(0.15)})
    text = _table_text([row], bench.BenchConfig(dense_budget=0))
    line = next(ln for ln in text.splitlines() if "1,000" in ln)
    cells = [c.strip() for c in line.split("│") if c.strip()]
    # Columns end: torch f+b, fwd, MB, dense f+b, fwd, MB, x torch, x dense.
    assert cells[-8:] == ["0.500", "0.167", "10", "-", "-", "-", "5.0x", "-"]
    assert not any(c.startswith("-") and c != "-" for c in cells)  # no negative extrapolations


def test_extrapolated_dense_rows_are_starred():
    row = {"gaussians": 1000, "resolution": "20x10", "mean_radius_px": 2.0, "pairs": 5000}
    row.update({"cpu-fast": _case(0.1), "torch": _case(0.5), "dense": _case(2.0, window="10x2")})
    text = _table_text([row], bench.BenchConfig())
    assert "2.00*" in text and "20x" in text


def test_negative_dense_budget_is_refused():
    with pytest.raises(SystemExit, match="--dense-budget must be >= 0"):
        entrypoint(["--dense-budget", "-5"])


def test_dense_extrapolation_refuses_noise():
    # 1 px: 0.10 s; a 201-px window: 0.30 s -> 1 ms per pixel, 0.10 + 0.2 * 10 at 2001 px.
    got = bench.extrapolate((0.05, 0.10), (0.15, 0.30), 201, 2001)
    assert got == pytest.approx((0.05 + 0.1 * 10, 0.10 + 0.2 * 10))
    # A window timed faster than one pixel is noise: no (negative) extrapolation.
    assert bench.extrapolate((0.05, 0.10), (0.04, 0.30), 201, 2001) is None
