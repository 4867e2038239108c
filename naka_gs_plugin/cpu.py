"""What this CPU can do, for the places that choose a dtype or a thread count (a leaf module).

- :func:`native_bf16`: bfloat16 convolutions are fast only with AVX-512 BF16 or AMX; elsewhere oneDNN
  emulates them, about 5x slower than float32 (the correction network's ``auto`` mode reads this).
- :func:`fit_threads`: PyTorch starts one thread per physical core of the *machine*, also inside a
  container limited to fewer CPUs (CPU affinity, a cgroup CPU quota); more threads than CPUs turns
  every OpenMP barrier into a wait for a descheduled thread. numba's kernels follow PyTorch's count.
- :func:`keep_freed_memory`: glibc's allocator settings for training, whose every step allocates and
  frees the same multi-megabyte tensors.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
from pathlib import Path
from typing import Optional, Tuple

import torch

_FITTED: dict = {}


def native_bf16() -> Tuple[bool, str]:
    """Whether bfloat16 convolutions run natively here, and why: the CPU has AVX-512 BF16 or AMX, and
    neither oneDNN nor ATen is capped below it (``ONEDNN_MAX_CPU_ISA``, ``ATEN_CPU_CAPABILITY``)."""
    if not (torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported()):
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


MMAP_THRESHOLD = 32 << 20
"""Allocations above this go straight to the kernel (glibc's largest allowed value; its default
starts at 128 KiB and adapts)."""
TRIM_THRESHOLD = 256 << 20
"""Freed memory kept at the top of the heap before glibc returns it to the kernel (default 128 KiB,
adapting). The most a training process keeps mapped beyond what it uses."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters, glibc's malloc.h


def keep_freed_memory() -> bool:
    """Have glibc's malloc keep freed blocks of up to ``MMAP_THRESHOLD`` mapped for reuse; False where
    the C library has no ``mallopt`` (macOS, Windows), which changes nothing there.

    Once the correction network has run in a process (lean mode, LOM 500x375), every training step's
    tensors were mapped fresh from the kernel and page-faulted: the SSIM loss's forward and backward took
    226 ms instead of 64, a full-size step on LOM shrub (95k Gaussians) 480 ms instead of 270 with the
    same images read from the cache (docs/cpu.md). Fixed thresholds (which also stop glibc adapting them)
    bring it back to 295 ms. Called after enhancement, before training; setting them beforehand does not
    help, the correction run changes the heap after it."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
