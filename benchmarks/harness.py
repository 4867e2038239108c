"""What the benches share: one measurement per fresh process, and that process's own peak memory; a
command's wall and peak memory (:func:`timed`).

Peak memory is the kernel's peak resident set size of the process (``VmHWM``), reset through
``/proc/self/clear_refs`` just before the measured work when only its increase is wanted.
(``getrusage``'s ``ru_maxrss`` would be wrong in a child: Linux carries the parent's value across
fork and exec.) A spawned process starts from a fresh interpreter, so its ``VmHWM`` is its own.
"""

from __future__ import annotations

import multiprocessing
import re
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Callable


def proc_status_bytes(field: str) -> int:
    """A memory field of ``/proc/self/status`` (``VmRSS``, ``VmHWM``, ...) in bytes."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024  # reported in kB
    raise RuntimeError(f"{field} missing from /proc/self/status")


def peak_rss() -> int:
    """Peak resident set size of this process (bytes), since its start or the last :func:`reset_peak_rss`."""
    return proc_status_bytes("VmHWM")


def reset_peak_rss() -> int:
    """Reset the kernel's peak-RSS mark of this process to its current RSS, and return that (bytes)."""
    with open("/proc/self/clear_refs", "w") as clear_refs:
        clear_refs.write("5")
    return proc_status_bytes("VmRSS")


def run_isolated(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in a fresh spawned process (``fn`` importable at module level); its result comes back."""
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


def timed(cmd: list, env: dict, log: Path) -> tuple[float, float]:
    """(wall s, peak RSS GB) of ``cmd`` under /usr/bin/time; its output goes to ``log``."""
    with open(log, "w") as out:
        res = subprocess.run(["/usr/bin/time", "-f", "TIME %e %M", *cmd], env=env, stdout=out, stderr=subprocess.STDOUT)
    text = log.read_text()
    if res.returncode != 0:
        sys.exit(f"[naka-gs bench] {cmd[0]} failed (exit {res.returncode}); see {log}")
    wall, rss_kb = re.findall(r"TIME ([\d.]+) (\d+)", text)[-1]
    return float(wall), int(rss_kb) / 2**20
