"""Compiled CPU tile rasterizer ("cpu-fast"): the autograd function and the entry points.

Same interface, conventions and results as :mod:`naka_gs_plugin.model.rasterize` (gsplat 1.4.0
``rasterization``, unpacked, pinhole). Every stage is compiled: projection and SH colours
(:mod:`~naka_gs_plugin.model.project_cpu_fast`, float64 inside, so float32 results are the float64
reference's rounded, within rounding of the torch path's float32 arithmetic), the depth sort (a
stable radix sort), the tile binning, compositing and its backward, and the per-Gaussian reduction.

The numba kernels live in :mod:`~naka_gs_plugin.model.rasterize_cpu_lists` (the depth sort and the tile lists:
the layout is described there) and :mod:`~naka_gs_plugin.model.rasterize_cpu_kernels` (compositing forward and
backward, generic and 8-wide float32, and the reduction). This module holds :class:`_TileComposite`, the autograd
function that runs them: it picks the 8-wide float32 kernels for float32 RGB renders whose row spans are wide enough
(``RGB32_MIN_RUN``) and keeps its large work arrays for the next render (a scratch pool); and the entry points
:func:`rasterization` and :func:`rasterize_to_pixels_cpu_fast`, whose first call per dtype gets the kernels ready
(:func:`warm_up`; compiling, caching them on disk and compiling them ahead in a child process are
:mod:`~naka_gs_plugin.model.compile_ahead`'s). :func:`profile_stages` times the stages
(:mod:`~naka_gs_plugin.model.rasterize_cpu_profile`). ``numba.set_num_threads`` sets the number of threads.
"""

from __future__ import annotations

import threading
from functools import partial
from typing import Dict, Literal, Optional, Tuple, Union

import numba
import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from naka_gs_plugin.cpu import untraced
from naka_gs_plugin.model import compile_ahead
from naka_gs_plugin.model.compile_ahead import compiling_in_background as compiling_in_background  # pipeline's
from naka_gs_plugin.model.project_cpu_fast import project_gaussians, sh_colors
from naka_gs_plugin.model.rasterize import (
    ALPHA_MAX,
    ALPHA_MIN,
    TILE_SIZE,
    RenderMode,
    rasterization_with_compositor,
)
from naka_gs_plugin.model.rasterize_cpu_kernels import (
    LANES,
    N_GRAD,
    _backward_kernel,
    _backward_kernel_rgb32,
    _forward_kernel,
    _forward_kernel_rgb32,
    _reduce_slots,
)
from naka_gs_plugin.model.rasterize_cpu_lists import (
    _bin_tiles,
    _gather_rows,
    _make_records,
    _row_spans,
    _tile_pixels,
    _visible_by_depth,
)
from naka_gs_plugin.model.rasterize_cpu_profile import _stage
from naka_gs_plugin.model.rasterize_cpu_profile import profile_stages as profile_stages  # for benchmarks

VIS_STORE_MAX = 1 << 27
"""Most ``exp(-sigma)`` values (one per row-span pixel of each list entry; ~1.4x the composited
pairs for trained-scene-like Gaussians) the forward keeps for the backward (512 MB in float32);
beyond, the backward recomputes them (slower, same results)."""

_MAX_LAST_F32 = 1 << 24
"""Tile lists at least this long take the generic kernels: the float32 kernels keep each pixel's
last entry in a float32 plane, exact below 2**24."""

RGB32_MIN_RUN = 5.5
"""Fewest span pixels per (list entry, tile row), on average over a render, for the 8-wide kernels:
below, most lanes of a half row idle and the generic kernels are faster (about 1.1x the time at
4.6 pixels, 0.85x at 6.5, 0.77x at 8.9 for a render's forward and backward: docs/cpu.md)."""


def span_counts(vis_start: Int[np.ndarray, " K1"], slot_y: Int[np.ndarray, "K 2"]) -> Tuple[int, int]:
    """A render's span pixels and (list entry, tile row) pairs over all its tiles: their ratio is the
    row-span width ``RGB32_MIN_RUN`` is compared with."""
    return int(vis_start[-1]), int((slot_y[:, 1] - slot_y[:, 0]).sum()) + len(slot_y)


def _spans_suit_lanes(
    tile_start: Int[np.ndarray, " T1"], vis_start: Int[np.ndarray, " K1"], slot_y: Int[np.ndarray, "K 2"]
) -> bool:
    """Whether a float32 RGB render's lists take the 8-wide kernels: wide enough row spans in its
    tiles (``RGB32_MIN_RUN``) and no list too long for their float32 entry counts."""
    if len(slot_y) == 0 or int(np.diff(tile_start).max()) >= _MAX_LAST_F32:
        return False
    pixels, rows = span_counts(vis_start, slot_y)
    return pixels >= RGB32_MIN_RUN * rows


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


_SCRATCH: Dict[Tuple[str, type], np.ndarray] = {}
_SCRATCH_LOCK = threading.Lock()


def _take_scratch(name: str, size: int, dtype: type) -> np.ndarray:
    """A scratch array of at least ``size`` elements, reused across renders: first writes to fresh
    memory (page faults) cost more than the kernels' own work on it. The caller owns it until it
    hands it back with :func:`_give_scratch` (concurrent renders get their own arrays)."""
    with _SCRATCH_LOCK:
        buf = _SCRATCH.pop((name, dtype), None)
    if buf is None or buf.size < size:
        buf = np.empty(max(size, 1), dtype=dtype)
    return buf


def _give_scratch(name: str, buf: np.ndarray) -> None:
    """Keep ``buf`` for the next render (only the largest one per name and dtype is kept)."""
    with _SCRATCH_LOCK:
        kept = _SCRATCH.get((name, buf.dtype.type))
        if kept is None or kept.size < buf.size:
            _SCRATCH[(name, buf.dtype.type)] = buf


class _ScratchLease:
    """Hands a scratch array back when the autograd node holding it is freed (not after its
    backward: ``retain_graph`` may run that again)."""

    def __init__(self, name: str, buf: np.ndarray):
        self.name, self.buf = name, buf

    def __del__(self):
        _give_scratch(self.name, self.buf)


def _balanced_tile_order(tile_start: np.ndarray) -> np.ndarray:
    """Non-empty tiles, ordered so that numba's static schedule (equal contiguous blocks of the
    ``prange`` per thread) gives every thread a similar share of list entries: sorted by entries,
    dealt round-robin. (numba's dynamic ``parallel_chunksize`` costs more than it saves here.)"""
    counts = np.diff(tile_start)
    order = np.argsort(-counts, kind="stable")
    order = order[: int(np.count_nonzero(counts))]
    n_threads = numba.get_num_threads()
    return np.concatenate([order[t::n_threads] for t in range(n_threads)])


def warm_up(dtype: torch.dtype = torch.float32) -> float:
    """Compile (or load from numba's disk cache) every kernel for ``dtype`` by rendering a tiny
    scene forward and backward (:func:`_render_tiny_scene`); returns the seconds taken and logs them once per dtype
    and process. Called by the first render of a dtype, after
    :func:`~naka_gs_plugin.model.compile_ahead.compile_in_background`'s child has finished, if there is one
    (:func:`~naka_gs_plugin.model.compile_ahead.warm_rasterizer` keeps that account)."""
    return compile_ahead.warm_rasterizer(dtype, _render_tiny_scene)


def _render_tiny_scene(dtype: torch.dtype) -> None:
    """Two Gaussians on an 8x8 camera, rendered forward and backward in RGB and RGB+ED: every kernel of ``dtype``
    runs (float32 RGB has kernels of its own)."""
    params = dict(
        means=torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]], dtype=dtype),
        quats=torch.tensor([[1.0, 0.1, 0.2, 0.3], [1.0, 0.0, 0.0, 0.0]], dtype=dtype),
        scales=torch.full((2, 3), 0.3, dtype=dtype),
        opacities=torch.tensor([0.5, 0.9], dtype=dtype),
        colors=torch.ones(2, 16, 3, dtype=dtype),
    )
    params = {k: v.requires_grad_() for k, v in params.items()}
    camera = dict(
        viewmats=torch.eye(4, dtype=dtype)[None],
        Ks=torch.tensor([[[8.0, 0, 4], [0, 8, 4], [0, 0, 1]]], dtype=dtype),
        width=8,
        height=8,
    )
    with torch.enable_grad():
        for render_mode in ("RGB", "RGB+ED"):  # float32 RGB has kernels of its own
            colors, alphas, _ = rasterization(
                **params,
                **camera,
                sh_degree=3,
                rasterize_mode="antialiased",
                render_mode=render_mode,
                absgrad=True,
            )
            (colors.sum() + alphas.sum()).backward()


def warm_training_kernels() -> None:
    """Compile (or load) the float32 kernels of a training step, the rasterizer's, SSIM's and compositing's: what
    :func:`~naka_gs_plugin.model.compile_ahead.compile_in_background`'s child runs
    (:func:`~naka_gs_plugin.model.compile_ahead.warm_training_kernels` with this rasterizer's :func:`warm_up`)."""
    compile_ahead.warm_training_kernels(warm_up)


class _TileComposite(torch.autograd.Function):
    """Front-to-back compositing over the tile lists; hand-written backward (see
    :mod:`~naka_gs_plugin.model.rasterize_cpu_kernels`)."""

    @staticmethod
    @untraced()
    def forward(
        ctx,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        backgrounds: Optional[Tensor],
        depths: Tensor,
        radii: Tensor,
        width: int,
        height: int,
        absgrad: bool,
    ) -> Tuple[Tensor, Tensor]:
        n_cams, n, dim = colors.shape
        dtype = colors.dtype
        np_dtype = np.float32 if dtype == torch.float32 else np.float64
        with _stage("sort+bin"):
            consts = np.array([0.5, ALPHA_MAX, ALPHA_MIN, 0.0], dtype=np_dtype)
            entries = _visible_by_depth(_np(radii), _np(opacities), _np(depths), consts[2])
            # One record per visible entry, in depth order; the kernels get a copy per list slot.
            records, boxes = _make_records(
                entries,
                _np(means2d).reshape(-1, 2),
                _np(conics).reshape(-1, 3),
                _np(opacities).reshape(-1),
                _np(colors).reshape(-1, dim),
                radii.reshape(-1).to(dtype).numpy(),
                consts,
                width,
                height,
            )
            tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
            tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
            xs = (torch.arange(width, dtype=dtype) + 0.5).numpy()  # pixel centres, as the torch path
            ys = (torch.arange(height, dtype=dtype) + 0.5).numpy()
            row_start, spans = _row_spans(records, boxes, ys)
            tile_start, tile_items, rec_start, rec_slots, vis_start, slot_y = _bin_tiles(
                boxes, entries, n, n_cams, tiles_x, tiles_y, *_tile_pixels(boxes, row_start, spans)
            )
            slot_records, slot_rows = _gather_rows(records, tile_items, row_start, boxes)
            kernel_args = (
                _balanced_tile_order(tile_start),
                tile_start,
                vis_start,
                slot_rows,
                slot_y,
                slot_records,
                xs,
                ys,
                consts,
                n_cams,
                width,
                height,
                spans,
            )
        rgb32 = dtype == torch.float32 and dim == 3 and _spans_suit_lanes(tile_start, vis_start, slot_y)
        with _stage("forward kernel"):
            if rgb32:
                kernel_args = kernel_args[:2] + kernel_args[3:] + (LANES,)
                out, t_final, last = _forward_kernel_rgb32(*kernel_args)
                extra, ctx.leases = (), []
            else:
                n_vis = int(vis_start[-1])
                vis_store = _take_scratch("vis", n_vis, np_dtype) if n_vis <= VIS_STORE_MAX else np.zeros(0, np_dtype)
                out, t_final, last = _forward_kernel(*kernel_args, vis_store)
                extra = (vis_store,)
                ctx.leases = [_ScratchLease("vis", vis_store)] if vis_store.size else []
        out = torch.from_numpy(out)
        t_final_t = torch.from_numpy(t_final).to(dtype)
        if backgrounds is not None:
            out = out + (t_final_t.reshape(n_cams, -1, 1) * backgrounds[:, None, :].detach()).reshape(-1, dim)
        ctx.save_for_backward(means2d, backgrounds)
        ctx.kernel_args = kernel_args + (t_final, last) + extra
        ctx.rgb32, ctx.t_final = rgb32, t_final
        ctx.slot_lists = (rec_start, rec_slots, entries)
        ctx.meta = (n_cams, n, dim, absgrad)
        return out.reshape(n_cams, height, width, dim), (1.0 - t_final_t).reshape(n_cams, height, width, 1)

    @staticmethod
    @untraced()
    def backward(ctx, grad_colors: Tensor, grad_alphas: Tensor):
        means2d, backgrounds = ctx.saved_tensors
        n_cams, n, dim, absgrad = ctx.meta
        t_final = ctx.t_final
        dtype = grad_colors.dtype
        grad_colors = grad_colors.reshape(n_cams, -1, dim)
        upstream = -grad_alphas.reshape(n_cams, -1).double()
        if backgrounds is not None:
            upstream = upstream + (grad_colors * backgrounds[:, None, :]).sum(-1).double()
        grad_q = torch.from_numpy(t_final) * upstream.reshape(-1)
        with _stage("backward kernel"):
            n_slots = ctx.slot_lists[1].shape[0]
            slot_dtype = np.float32 if ctx.rgb32 else np.float64
            slot_buf = _take_scratch("slots", n_slots * (N_GRAD + dim), slot_dtype)
            slots = slot_buf[: n_slots * (N_GRAD + dim)].reshape(n_slots, N_GRAD + dim)
            kernel, grad_dtype = (
                (_backward_kernel_rgb32, torch.float32) if ctx.rgb32 else (_backward_kernel, torch.float64)
            )
            kernel(
                *ctx.kernel_args,
                grad_colors.reshape(-1, dim).to(grad_dtype).contiguous().numpy(),
                grad_q.to(grad_dtype).contiguous().numpy(),
                slots,
            )
        with _stage("reduce+scatter"):
            g_means2d = torch.zeros(n_cams, n, 2, dtype=dtype)
            g_abs = torch.zeros(n_cams, n, 2, dtype=dtype)
            g_conics = torch.zeros(n_cams, n, 3, dtype=dtype)
            g_opac = torch.zeros(n_cams, n, dtype=dtype)
            g_colors = torch.zeros(n_cams, n, dim, dtype=dtype)
            outs = (g_means2d, g_abs, g_conics, g_opac, g_colors)
            _reduce_slots(slots, *ctx.slot_lists, *(g.view(n_cams * n, -1).numpy() for g in outs))
            _give_scratch("slots", slot_buf)
        if absgrad:
            means2d.absgrad = g_abs
        grad_bg = None
        if backgrounds is not None and ctx.needs_input_grad[4]:
            t = torch.from_numpy(t_final).to(dtype).reshape(n_cams, -1, 1)
            grad_bg = (grad_colors * t).sum(1)
        return g_means2d, g_conics, g_opac, g_colors, grad_bg, None, None, None, None, None


def rasterize_to_pixels_cpu_fast(
    means2d: Float[Tensor, "C N 2"],
    conics: Float[Tensor, "C N 3"],
    colors: Float[Tensor, "C N D"],
    opacities: Float[Tensor, "C N"],
    depths: Float[Tensor, "C N"],
    radii: Int[Tensor, "C N"],
    width: int,
    height: int,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    absgrad: bool = False,
) -> Tuple[Float[Tensor, "C H W D"], Float[Tensor, "C H W 1"]]:
    """Composite screen-space Gaussians front to back with the compiled tile kernels.

    Same semantics, inputs and outputs as
    :func:`~naka_gs_plugin.model.rasterize.rasterize_to_pixels_sparse` (including
    ``means2d.absgrad`` when ``absgrad``); CPU tensors only, float32 or float64.
    """
    if means2d.device.type != "cpu":
        raise ValueError(f"the cpu-fast rasterizer needs CPU tensors, got {means2d.device} -- use gsplat on CUDA")
    if colors.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the cpu-fast rasterizer supports float32/float64, got {colors.dtype}")
    warm_up(colors.dtype)
    return _TileComposite.apply(means2d, conics, opacities, colors, backgrounds, depths, radii, width, height, absgrad)


def rasterization(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, " N"],
    colors: Union[Tensor, Tuple[Tensor, Tensor]],
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    sh_degree: Optional[int] = None,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    absgrad: bool = False,
    eps2d: float = 0.3,
) -> Tuple[Float[Tensor, "C H W X"], Float[Tensor, "C H W 1"], Dict]:
    """:func:`naka_gs_plugin.model.rasterize.rasterization` (gsplat 1.4.0 interface, same outputs
    and ``meta``) with compiled projection, SH colours and compositing; CPU tensors only. With ``sh_degree``,
    ``colors`` may also be splatfacto's ``(features_dc [N, 3], features_rest [N, K - 1, 3])``, which the SH
    kernels read as they are (:func:`~naka_gs_plugin.model.project_cpu_fast.sh_colors`)."""
    if means.device.type != "cpu":
        raise ValueError(f"the cpu-fast rasterizer needs CPU tensors, got {means.device} -- use gsplat on CUDA")
    if means.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the cpu-fast rasterizer supports float32/float64, got {means.dtype}")
    warm_up(means.dtype)
    return rasterization_with_compositor(
        partial(rasterize_to_pixels_cpu_fast, absgrad=absgrad),
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        sh_degree=sh_degree,
        backgrounds=backgrounds,
        render_mode=render_mode,
        rasterize_mode=rasterize_mode,
        eps2d=eps2d,
        project=project_gaussians,
        shade=sh_colors,
    )
