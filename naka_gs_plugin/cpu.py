"""What this CPU can do, for the places that choose a dtype or a thread count (a leaf module).

- :func:`cpu_has`: an ISA feature (AVX2, AVX-512, AVX-512 BF16, AMX), by PyTorch's probe or the kernel's flags.
- :func:`native_bf16`: bfloat16 convolutions are fast only with AVX-512 BF16 or AMX; elsewhere oneDNN
  emulates them, several times slower than float32 (docs/cpu.md; the correction network's ``auto``
  mode reads this).
- :func:`fit_threads`: PyTorch starts one thread per physical core of the *machine*, also inside a
  container limited to fewer CPUs (CPU affinity, a cgroup CPU quota); more threads than CPUs turns
  every OpenMP barrier into a wait for a descheduled thread. numba's kernels follow PyTorch's count.
- :func:`core_lent`, :func:`reclaim_core`: one core left to a child process (the first run's kernel compile)
  while the main process works on the others, and taken back as soon as the child exits: the main process
  checks between its work items (the enhancement's views), since an OpenMP thread count is set per thread.
- :func:`torch_threads_kept`: numba's OpenMP pool, started by the first parallel kernel, resets the OpenMP
  runtime it shares with PyTorch (hence PyTorch's thread count) to numba's; every caller of numba kernels
  keeps PyTorch's count with it.
- :func:`numba_fast_path`: a compiled fast path, or None where numba does not import.
- :func:`untraced`: Python tracing suspended around compiled calls, as around a C extension's.
- :func:`keep_freed_memory`: glibc's allocator thresholds for training, whose every step allocates and
  frees the same multi-megabyte tensors (:func:`glibc`: the C library's allocator calls, if glibc).
"""

from __future__ import annotations

import ctypes
import functools
import importlib
import math
import os
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Dict, Iterator, Optional, Tuple

import torch

_FITTED: dict = {}
_LENT: Dict[int, Tuple[subprocess.Popen, int]] = {}
"""Children holding a core of this process's (:func:`core_lent`), by pid, with the thread count to restore."""


CPUINFO = Path("/proc/cpuinfo")
_CPUINFO_FLAG = {"avx512": "avx512f"}
"""PyTorch's name of a feature -> the kernel's flag in ``/proc/cpuinfo``, where the two differ."""


def cpu_has(feature: str) -> bool:
    """Whether the CPU has ``feature`` (``avx2``, ``avx512``, ``avx512_bf16``, ``amx_tile``): PyTorch's probe
    ``torch.cpu._is_<feature>_supported``, which torch < 2.3 lacks; there the kernel's flags in ``/proc/cpuinfo``
    (Linux), else False (float32 and the generic kernels are the safe choice)."""
    probe = getattr(torch.cpu, f"_is_{feature}_supported", None)
    if probe is not None:
        return bool(probe())
    try:
        return _CPUINFO_FLAG.get(feature, feature) in CPUINFO.read_text().split()
    except OSError:
        return False


def native_bf16() -> Tuple[bool, str]:
    """Whether bfloat16 convolutions run natively here, and why: the CPU has AVX-512 BF16 or AMX, and
    neither oneDNN nor ATen is capped below it (``ONEDNN_MAX_CPU_ISA``, ``ATEN_CPU_CAPABILITY``)."""
    if not (cpu_has("avx512_bf16") or cpu_has("amx_tile")):
        return False, "this CPU has neither AVX-512 BF16 nor AMX"
    if not torch.ops.mkldnn._is_mkldnn_bf16_supported():
        return False, "oneDNN has no bfloat16 kernels here (ONEDNN_MAX_CPU_ISA caps it)"
    capability = torch.backends.cpu.get_cpu_capability()
    if not capability.startswith("AVX512"):
        return False, f"PyTorch's kernels run at {capability} (ATEN_CPU_CAPABILITY caps them)"
    return True, "this CPU has native bfloat16 (AVX-512 BF16 or AMX)"


def cgroup_cpu_limit(root: Path = Path("/sys/fs/cgroup")) -> Optional[float]:
    """CPUs allowed by the cgroup CPU quota (v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``), or None."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 or period <= 0 else quota / period
    except (OSError, ValueError):
        return None


def usable_cpus() -> Tuple[int, str]:
    """How many CPUs this process may run on at once, and what limits it."""
    count, why = os.cpu_count() or 1, "CPUs in the machine"
    if hasattr(os, "sched_getaffinity"):
        affinity = len(os.sched_getaffinity(0))
        if affinity < count:
            count, why = affinity, "CPU affinity"
    quota = cgroup_cpu_limit()
    if quota is not None and math.ceil(quota) < count:
        count, why = max(1, math.ceil(quota)), "the cgroup CPU quota"
    return count, why


def fit_threads() -> int:
    """Cap PyTorch's intra-op threads (and so numba's) at :func:`usable_cpus`, logged once per process
    when it lowers them; an explicit ``OMP_NUM_THREADS`` or ``torch.set_num_threads`` below is kept."""
    usable, why = usable_cpus()
    threads = torch.get_num_threads()
    if threads > usable:
        torch.set_num_threads(usable)
        if "logged" not in _FITTED:
            _FITTED["logged"] = True
            print(f"[naka-gs] using {usable} threads instead of {threads}: {usable} CPUs usable ({why})", flush=True)
        return usable
    return threads


def glibc():
    """glibc's ``mallopt``/``malloc_trim`` through ctypes, or None off glibc (macOS, musl, Windows)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # mallopt parameters, glibc's malloc.h
MMAP_THRESHOLD = 32 << 20
"""Blocks above this are mapped from the kernel and unmapped on free (glibc's largest allowed value)."""
TRIM_THRESHOLD = 256 << 20
"""Freed memory kept at the top of the heap before glibc hands it back: the most a process keeps
mapped beyond what it uses."""


@functools.cache
def numba_fast_path(module: str, name: str):
    """``module.name``, a numba-compiled fast path, or None where numba does not import: a broken install only
    loses the fast path, and the caller runs its PyTorch reference (as the rasterizer's ``auto`` falls back)."""
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError:
        return None


@contextmanager
def torch_threads_kept() -> Iterator[None]:
    """PyTorch's intra-op thread count as it was before the block, whatever numba's pool did to it (module
    docstring)."""
    threads = torch.get_num_threads()
    try:
        yield
    finally:
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


@contextmanager
def core_lent(child: subprocess.Popen) -> Iterator[None]:
    """PyTorch's intra-op threads (and so numba's) one fewer for the block while ``child`` runs, where they would
    otherwise fill every usable CPU: a busy thread more than there are cores makes every parallel region wait at
    its barrier for the thread that shares a core. The count returns at :func:`reclaim_core` once the child has
    exited, and at the block's end in any case."""
    with torch_threads_kept():
        threads = fit_threads()
        if threads >= usable_cpus()[0] and threads > 1 and child.poll() is None:
            torch.set_num_threads(threads - 1)
            _LENT[child.pid] = (child, threads)
        try:
            yield
        finally:
            _LENT.pop(child.pid, None)


def reclaim_core() -> None:
    """Take back the core of every :func:`core_lent` child that has exited (cheap: one ``poll`` each); called
    between the work items of a block, on the thread that runs them."""
    for pid, (child, threads) in list(_LENT.items()):
        if child.poll() is not None:
            del _LENT[pid]
            torch.set_num_threads(threads)


@contextmanager
def untraced() -> Iterator[None]:
    """Python tracing (``sys.settrace``) suspended in this thread for the block, as over a C extension's call.

    numba's dispatcher runs Python helpers (``numba.core.serialize._numba_unpickle``) at every compiled call;
    an exception a trace function raises there comes out as ``SystemError`` instead of itself. nerfstudio's
    viewer interrupts a stale render exactly so (``SetTrace(check_interrupt)`` raises ``IOChangeException`` at
    the next traced line) and catches only its own exception: the ``SystemError`` killed its render thread.
    With the block untraced, the interrupt lands on the first line after it."""
    trace = sys.gettrace()
    if trace is None:
        yield
        return
    sys.settrace(None)
    try:
        yield
    finally:
        sys.settrace(trace)


def keep_freed_memory() -> bool:
    """Have glibc keep freed blocks of up to ``MMAP_THRESHOLD`` in the heap for reuse, for training, whose
    every step allocates and frees the same multi-megabyte tensors; False off glibc (nothing changes).

    A fresh process gets this from glibc's adaptive thresholds, but they stop adapting for good once
    anything sets them with ``mallopt`` (the lean correction forward does, :func:`naka_gs_plugin.enhance.
    lean_ops.reuse_freed_memory`). Pinned at glibc's initial 128 KiB, every training tensor is mapped
    fresh and page-faulted on each step, which made full-size training steps much slower (figures:
    records/2026-11-26-allocator-after-correction.md)."""
    libc = glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
