"""Getting the cpu-fast kernels compiled: the table of every numba kernel a training step runs (the rasterizer's,
SSIM's and the image compositing's), the rasterizer's warm-up account, numba's disk cache, and the child process
that compiles the kernels ahead, beside the enhancement.

Kernels are compiled on first use per dtype (tens of seconds) and cached on disk by numba (``cache=True``: next to
their source files, or under ``NUMBA_CACHE_DIR`` / the user cache directory when the package directory is not
writable). The rasterizer's first render of a dtype gets its kernels ready
(:func:`~naka_gs_plugin.model.rasterize_cpu_fast.warm_up`, kept account of by :func:`warm_rasterizer`) and logs how
long the compile or cache load took. The naka-gs pipeline starts the float32 kernels' compile in a child process
before it enhances the training images, on one thread fewer until the child exits (:func:`compiling_in_background`),
so that on a first run the two overlap; the first render waits for the child, then loads the kernels from the disk
cache (or compiles them itself if the child failed).

The rasterizer (:mod:`~naka_gs_plugin.model.rasterize_cpu_fast`) imports this module, not the other way round: its
first render waits here for the child. So the child names the rasterizer's module (:data:`CHILD_MODULE`) instead of
this module importing it, and :func:`warm_training_kernels` is handed the rasterizer's warm-up.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Dict, Iterator, Optional, Set, Tuple

import numba
import torch
from rich.console import Console

from naka_gs_plugin.cpu import core_lent, torch_threads_kept, usable_cpus

CONSOLE = Console(width=120)
"""rich's console, as nerfstudio's (this module imports without nerfstudio, e.g. on the GPU machine)."""

TRAINING_KERNELS: Tuple[Tuple[str, str, Tuple[str, ...]], ...] = (
    # whose        module (of naka_gs_plugin.model)  its kernels
    ("rasterizer", "rasterize_cpu_lists", (
        "_visible_by_depth", "_make_records", "_row_spans", "_tile_pixels", "_bin_tiles", "_gather_rows",
    )),
    ("rasterizer", "rasterize_cpu_kernels", (
        "_forward_kernel", "_backward_kernel", "_forward_kernel_rgb32", "_backward_kernel_rgb32", "_reduce_slots",
    )),
    ("rasterizer", "project_cpu_fast", ("_project_forward", "_project_backward", "_sh_forward", "_sh_backward")),
    ("SSIM", "ssim_cpu_fast", ("_forward_kernel", "_backward_kernel")),
    ("compositing", "composite_cpu_fast", ("_forward_kernel", "_backward_kernel")),
)  # fmt: skip
"""Every numba kernel a training step calls from Python (the helpers they call compile into them): the rasterizer's
(tile lists, compositing, projection and SH colours), SSIM's and the image compositing's, each row as (whose, module of
``naka_gs_plugin.model``, kernel names). :func:`kernels` reads them."""


def kernels(whose: Optional[str] = None) -> Tuple:
    """The kernels of :data:`TRAINING_KERNELS` (only ``whose``'s, if given). Their modules are imported here, by
    name, when first asked for: SSIM's imports ``pytorch_msssim``, which the rasterizer does without (it runs without
    nerfstudio on the GPU machine)."""
    return tuple(
        getattr(importlib.import_module(f"naka_gs_plugin.model.{module}"), name)
        for row_whose, module, names in TRAINING_KERNELS
        if whose in (None, row_whose)
        for name in names
    )


def _cache_index_path(kernel) -> Optional[str]:
    """The file in which numba's disk cache lists ``kernel``'s compiled signatures (one index per kernel), or None
    where this numba lays its cache out otherwise. numba has no public API for it: this reads private attributes of
    its dispatchers (``_cache._cache_file._index_path``, numba 0.60 to 0.68), the one place this package does."""
    try:
        return kernel._cache._cache_file._index_path
    except AttributeError:  # a numba without this cache layout: assume nothing is on disk
        return None


def kernels_on_disk() -> bool:
    """Whether numba's disk cache holds an index for every kernel a training step runs (whether it is
    current for this source and machine, numba decides when it loads)."""
    return all(path is not None and os.path.exists(path) for path in map(_cache_index_path, kernels()))


_READY: Dict[torch.dtype, float] = {}
"""Seconds the rasterizer's kernels took to get ready in this process (:func:`warm_rasterizer`), by dtype."""
_WARMING: Set[torch.dtype] = set()
"""The dtypes whose kernels :func:`warm_rasterizer` is getting ready (its tiny render asks again)."""
_BACKGROUND: Dict[torch.dtype, subprocess.Popen] = {}
"""The running background compile (:func:`compile_in_background`), by the dtype of its kernels."""

_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])

CHILD_MODULE = "naka_gs_plugin.model.rasterize_cpu_fast"
"""The module the child process imports (as ``m``): the rasterizer, whose tiny render compiles its kernels. Named
here, not imported: it imports this module."""


def child_code(statement: str) -> str:
    """Python code running ``statement`` with :data:`CHILD_MODULE` of this very checkout imported as ``m``: numba
    caches a kernel per source file, and ``python -c`` would put the working directory first on ``sys.path``, where
    another checkout of the package may be (a worktree, a clone)."""
    return f"import sys; sys.path.insert(0, {_PACKAGE_ROOT!r}); import {CHILD_MODULE} as m; {statement}"


BACKGROUND_COMMAND = (sys.executable, "-c", child_code("m.warm_training_kernels()"))
"""The child process of :func:`compile_in_background`: :func:`warm_training_kernels` with the rasterizer's warm-up
(:func:`~naka_gs_plugin.model.rasterize_cpu_fast.warm_training_kernels`)."""


def compile_in_background() -> bool:
    """Start compiling the float32 kernels of a training step in a child process (one thread), unless
    they are on disk already or this process may use only one CPU; returns whether it started one.
    numba compiles in Python and holds the GIL, so a thread would stall the caller's work, while a
    process compiles on another core during what the caller does meanwhile (the training images'
    enhancement, the seed points) and leaves the kernels in numba's disk cache. The first render waits
    for it (:func:`warm_rasterizer`), then loads them; if the child failed, that render compiles them itself,
    as without a child."""
    if torch.float32 in _READY or torch.float32 in _BACKGROUND or usable_cpus()[0] < 2 or kernels_on_disk():
        return False
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    _BACKGROUND[torch.float32] = subprocess.Popen(
        BACKGROUND_COMMAND, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    return True


@contextmanager
def compiling_in_background() -> Iterator[bool]:
    """:func:`compile_in_background` for the block, which leaves the child its core until it exits
    (:func:`~naka_gs_plugin.cpu.core_lent`: the block takes it back at its
    :func:`~naka_gs_plugin.cpu.reclaim_core` calls). Yields whether a child started; the thread count is
    restored after the block."""
    if not compile_in_background():
        yield False
        return
    with core_lent(_BACKGROUND[torch.float32]):
        yield True


def warm_training_kernels(warm_rasterizer: Callable[[torch.dtype], float]) -> None:
    """Compile (or load) the float32 kernels of a training step: the rasterizer's (``warm_rasterizer``: its
    :func:`~naka_gs_plugin.model.rasterize_cpu_fast.warm_up`), SSIM's and compositing's, by running each on a tiny
    input forward and backward (:func:`compile_in_background`'s child)."""
    from naka_gs_plugin.model.composite_cpu_fast import composite_cpu_fast
    from naka_gs_plugin.model.ssim import FAST_TAPS, SSIMLoss

    warm_rasterizer(torch.float32)
    size = FAST_TAPS + 1
    render = torch.rand(size, size, 3, requires_grad=True)
    alpha = torch.rand(size, size, 1, requires_grad=True)
    gain, offset = torch.ones(3, requires_grad=True), torch.zeros(3, requires_grad=True)
    composite_cpu_fast(render, alpha, torch.zeros(3)).sum().backward()
    image = composite_cpu_fast(render, alpha, torch.zeros(3), gain, offset).permute(2, 0, 1)[None]
    SSIMLoss(data_range=1.0, size_average=True, channel=3)(image, torch.rand(1, 3, size, size)).backward()


def _wait_for_background(dtype: torch.dtype) -> None:
    child = _BACKGROUND.pop(dtype, None)
    if child is None:
        return
    if child.poll() is None:
        started = time.perf_counter()
        child.wait()
        CONSOLE.log(
            f"[naka-gs] cpu-fast rasterizer: waited {time.perf_counter() - started:.1f} s for the background compile",
            markup=False,
        )
    if child.returncode != 0:
        CONSOLE.log(
            f"[naka-gs] cpu-fast rasterizer: background compile failed (exit code {child.returncode}); compiling here",
            markup=False,
        )


def warm_rasterizer(dtype: torch.dtype, render: Callable[[torch.dtype], None]) -> float:
    """Get the rasterizer's ``dtype`` kernels ready once per dtype and process: wait for
    :func:`compile_in_background`'s child if there is one, then ``render(dtype)`` (a tiny render forward and
    backward, which compiles the kernels or loads them from numba's disk cache); returns the seconds taken (0 when
    ready already, or while ``render`` runs) and logs them."""
    if dtype in _READY or dtype in _WARMING:
        return 0.0
    _wait_for_background(dtype)
    _WARMING.add(dtype)
    started = time.perf_counter()
    # The first parallel kernel starts numba's OpenMP pool: keep the caller's PyTorch thread count.
    try:
        with torch_threads_kept():
            render(dtype)
    finally:
        _WARMING.discard(dtype)
    seconds = time.perf_counter() - started
    misses = sum(sum(k.stats.cache_misses.values()) for k in kernels("rasterizer"))
    how = "compiled (and cached on disk)" if misses else "loaded from numba's disk cache"
    CONSOLE.log(
        f"[naka-gs] cpu-fast rasterizer: {dtype} kernels {how} in {seconds:.1f} s; {numba.get_num_threads()} threads",
        markup=False,
    )
    _READY[dtype] = seconds
    return seconds
