"""The benches' harness: a fresh process per measurement, whose peak RSS is its own."""

import numpy as np

from benchmarks.harness import peak_rss, reset_peak_rss, run_isolated

MB = 2**20


def _touch(mb: int) -> tuple:
    """(peak RSS of the whole process, peak increase over the RSS before touching ``mb`` MB), in bytes."""
    base = reset_peak_rss()
    block = np.ones(mb * MB, dtype=np.uint8)
    del block
    return peak_rss(), peak_rss() - base


def test_child_peak_is_its_own_not_the_parents():
    held = np.ones(1536 * MB, dtype=np.uint8)  # the parent's peak, which ru_maxrss would carry into the child
    whole, increase = run_isolated(_touch, 100)
    assert 95 * MB <= increase <= 150 * MB
    assert whole < held.nbytes < peak_rss()  # the child's imports (torch included) and 100 MB, not the parent's
