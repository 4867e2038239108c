"""Compiled CPU tile rasterizer ("cpu-fast"): numba kernels with a hand-written backward.

Same interface, conventions and results as :mod:`naka_gs_plugin.model.rasterize` (gsplat 1.4.0
``rasterization``, unpacked, pinhole): projection and SH colours stay in torch autograd (they are a
share of the time, see the stage profile of ``naka-gs-bench-raster``); only the compositing step, where
eager torch has to materialise every Gaussian-pixel pair, is compiled.

Layout (as gsplat's CUDA path): the image is cut into 16x16 tiles; every visible Gaussian
(``radius > 0``, ``opacity >= 1/255``) is listed, in stable depth order, in each tile its pixel box
(:func:`~naka_gs_plugin.model.projection.pixel_bounds`) overlaps. Unlike gsplat, which evaluates
every Gaussian of a tile, a Gaussian only touches the pixels of its box, so exactly the pairs of the
torch path are composited. Forward (``prange`` over tiles): front to back with
``alpha = min(0.999, opacity * exp(-sigma))``, pairs with ``sigma < 0`` or ``alpha < 1/255``
skipped, a pixel stops *before* the pair that would bring its transmittance to ``<= 1e-4``;
transmittance is carried in float64 and the final transmittance and the number of list entries up
to the last contributing one are stored per pixel. Backward (``prange`` over tiles): each pixel's
list is walked back to front from that last entry, recovering the transmittance by division, with
the gradients for 2D means (and their per-pixel absolute values, gsplat's ``absgrad``), conics,
opacities and colours summed per (tile, list entry) slot; a serial pass then adds the slots up per
Gaussian, so there are no races and the result does not depend on the thread count.

On each row of its box a Gaussian visits only the columns of its lenient ``alpha >= 1/255`` ellipse
(the torch path's enumeration). ``sigma`` and ``alpha`` are computed in the inputs' dtype,
operation for operation as the torch path (so the same pairs pass the 1/255 test, and the
backward re-derives exactly the forward's alphas); gradients accumulate in float64. No
``fastmath``: contraction into FMAs or approximate ``exp`` would let the forward, the backward and
the torch path disagree on pairs at the thresholds. Kernels are compiled on first use per dtype
(tens of seconds) and cached on disk by numba (``cache=True``: next to this file, or under
``NUMBA_CACHE_DIR`` / the user cache directory when the package directory is not writable); the
first call logs how long the compile or cache load took. ``numba.set_num_threads`` sets the
number of threads.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from functools import partial
from typing import Dict, Iterator, Literal, Optional, Tuple

import numba
import numpy as np
import torch
from jaxtyping import Float, Int
from nerfstudio.utils.rich_utils import CONSOLE
from numba import njit, prange
from torch import Tensor

from naka_gs_plugin.model.projection import pixel_bounds
from naka_gs_plugin.model.rasterize import (
    _ENUM_SLACK,
    ALPHA_MAX,
    ALPHA_MIN,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    RenderMode,
    rasterization_with_compositor,
)

N_GRAD = 8
"""Per-Gaussian gradient columns before the colours: d means2d (2), |d means2d| (2), d conics (3),
d opacity (1)."""

REC_COLORS = 10
"""Record layout per visible entry, in the inputs' dtype: mean x, y (0, 1), conic a, b, c (2..4),
opacity (5), pixel box x_lo, x_hi, y_lo, y_hi (6..9, exact small integers), colours (10..)."""


@njit(cache=True)
def _bin_tiles(
    boxes: np.ndarray, cams: np.ndarray, n_cams: int, tiles_x: int, tiles_y: int
) -> Tuple[np.ndarray, np.ndarray]:
    """CSR lists, per tile, of the record indices whose box overlaps it, in record (depth) order."""
    tiles_per_cam = tiles_x * tiles_y
    counts = np.zeros(n_cams * tiles_per_cam + 1, dtype=np.int64)
    for j in range(boxes.shape[0]):
        base = cams[j] * tiles_per_cam
        for ty in range(boxes[j, 2] // TILE_SIZE, boxes[j, 3] // TILE_SIZE + 1):
            for tx in range(boxes[j, 0] // TILE_SIZE, boxes[j, 1] // TILE_SIZE + 1):
                counts[base + ty * tiles_x + tx + 1] += 1
    tile_start = np.cumsum(counts)
    fill = tile_start[:-1].copy()
    tile_items = np.empty(tile_start[-1], dtype=np.int32)
    for j in range(boxes.shape[0]):
        base = cams[j] * tiles_per_cam
        for ty in range(boxes[j, 2] // TILE_SIZE, boxes[j, 3] // TILE_SIZE + 1):
            for tx in range(boxes[j, 0] // TILE_SIZE, boxes[j, 1] // TILE_SIZE + 1):
                tile = base + ty * tiles_x + tx
                tile_items[fill[tile]] = j
                fill[tile] += 1
    return tile_start, tile_items


@njit(cache=True, inline="always")
def _alpha(dx, dy, a, b, c, opacity, consts):
    """``(vis, raw, alpha)`` of one pair in the inputs' dtype; ``alpha = 0`` when skipped.

    ``consts`` = (0.5, ALPHA_MAX, ALPHA_MIN, 0) in that dtype, so that nothing is promoted to float64
    and the arithmetic is the torch path's, operation for operation.
    """
    sigma = consts[0] * (a * dx * dx + c * dy * dy) + b * dx * dy
    vis = np.exp(-sigma)
    raw = opacity * vis
    alpha = min(raw, consts[1])
    if sigma < 0 or alpha < consts[2]:
        alpha = consts[3]
    return vis, raw, alpha


@njit(cache=True, inline="always")
def _ellipse_level(a, b, c, opacity):
    """``(level, det)`` in float64 of the lenient ``alpha >= 1/255`` ellipse ``sigma <= level``."""
    level = np.log(255.0 * np.float64(opacity)) * (1.0 + _ENUM_SLACK) + _ENUM_SLACK
    return level, np.float64(a) * c - np.float64(b) * b


@njit(cache=True, inline="always")
def _row_span(dy, mx, a, b, level, det, bx0, bx1):
    """Columns ``[lo, hi]`` of box columns ``[bx0, bx1]`` on a row ``dy = mean.y - centre.y`` that
    can be inside the lenient ellipse (as the torch path enumerates them); the exact per-pair test
    still decides. Falls back to the box for degenerate conics."""
    if not (a > 0 and det > 0 and level < np.inf):
        return bx0, bx1
    dy64 = np.float64(dy)
    disc = 2.0 * a * level - dy64 * dy64 * det
    if disc < 0:
        return 1, 0
    root = np.sqrt(disc)
    t_lo = (-b * dy64 - root) / a
    t_hi = (-b * dy64 + root) / a
    # Clip in float64 before converting: the span can exceed int64 for near-degenerate conics.
    lo = np.int64(max(np.float64(bx0), np.ceil(mx - t_hi - 0.5)))
    hi = np.int64(min(np.float64(bx1), np.floor(mx - t_lo - 0.5)))
    return lo, hi


@njit(cache=True, inline="always")
def _tile_box(tile, tiles_x, tiles_y, width, height):
    """``(camera, x0, y0, x1, y1)`` of a global tile index; ``x1``, ``y1`` exclusive."""
    cam = tile // (tiles_x * tiles_y)
    ty = (tile % (tiles_x * tiles_y)) // tiles_x
    x0, y0 = (tile % tiles_x) * TILE_SIZE, ty * TILE_SIZE
    return cam, x0, y0, min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)


@njit(parallel=True, cache=True)
def _forward_kernel(tile_order, tile_start, tile_items, records, xs, ys, consts, n_cams, width, height):
    """Composite every tile; returns colours without background, T_final (f64) and last entries."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_dim = records.shape[1] - REC_COLORS
    out = np.zeros((n_cams * height * width, n_dim), dtype=records.dtype)
    t_final = np.ones(n_cams * height * width, dtype=np.float64)
    last = np.zeros(n_cams * height * width, dtype=np.int32)
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        n_pix = tw * (y1 - y0)
        trans = np.ones(n_pix, dtype=np.float64)
        done = np.zeros(n_pix, dtype=np.bool_)
        acc = np.zeros((n_pix, n_dim), dtype=np.float64)
        last_local = np.zeros(n_pix, dtype=np.int32)
        alive = n_pix
        for k in range(s, e):
            rec = records[tile_items[k]]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            bx0, bx1 = max(np.int64(rec[6]), x0), min(np.int64(rec[7]), x1 - 1)
            by0, by1 = max(np.int64(rec[8]), y0), min(np.int64(rec[9]), y1 - 1)
            level, det = _ellipse_level(a, b, c, opacity)
            for py in range(by0, by1 + 1):
                dy = my - ys[py]
                lo, hi = _row_span(dy, mx, a, b, level, det, bx0, bx1)
                for px in range(lo, hi + 1):
                    i = (py - y0) * tw + (px - x0)
                    if done[i]:
                        continue
                    alpha = _alpha(mx - xs[px], dy, a, b, c, opacity, consts)[2]
                    if alpha == 0:
                        continue
                    t_next = trans[i] * (1.0 - np.float64(alpha))
                    if t_next <= TRANSMITTANCE_MIN:
                        done[i] = True
                        alive -= 1
                        continue
                    weight = np.float64(alpha) * trans[i]
                    for d in range(n_dim):
                        acc[i, d] += weight * rec[REC_COLORS + d]
                    trans[i] = t_next
                    last_local[i] = k - s + 1
            if alive == 0:
                break
        for i in range(n_pix):
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            for d in range(n_dim):
                out[p, d] = acc[i, d]
            t_final[p] = trans[i]
            last[p] = last_local[i]
    return out, t_final, last


@njit(parallel=True, cache=True)
def _backward_kernel(
    tile_order,
    tile_start,
    tile_items,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    t_final,
    last,
    grad_colors,
    grad_q,
):
    """Per (tile, list entry) gradient slots [K, N_GRAD + D], walking each pixel back to front.

    ``grad_colors`` [P, D] is dL/d(colour without background) and ``grad_q`` [P] is
    ``T_final * (dL/dcolour . background - dL/dalpha)``: the upstream term every pair's
    transmittance derivative carries.
    """
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_dim = records.shape[1] - REC_COLORS
    slots = np.zeros((tile_items.shape[0], N_GRAD + n_dim), dtype=np.float64)
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s = tile_start[tile]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        n_pix = tw * (y1 - y0)
        trans = np.empty(n_pix, dtype=np.float64)
        behind = np.zeros(n_pix, dtype=np.float64)
        last_local = np.empty(n_pix, dtype=np.int32)
        gcol = np.empty((n_pix, n_dim), dtype=np.float64)
        gq = np.empty(n_pix, dtype=np.float64)
        k_end = 0
        for i in range(n_pix):
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            trans[i] = t_final[p]
            last_local[i] = last[p]
            k_end = max(k_end, last[p])
            gq[i] = grad_q[p]
            for d in range(n_dim):
                gcol[i, d] = grad_colors[p, d]
        gcolor = np.empty(n_dim, dtype=np.float64)
        for kk in range(k_end - 1, -1, -1):
            rec = records[tile_items[s + kk]]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            bx0, bx1 = max(np.int64(rec[6]), x0), min(np.int64(rec[7]), x1 - 1)
            by0, by1 = max(np.int64(rec[8]), y0), min(np.int64(rec[9]), y1 - 1)
            level, det = _ellipse_level(a, b, c, opacity)
            # Scalars (kept in registers) for the geometry, the colour part in a small array.
            g_mx = g_my = g_absx = g_absy = g_ca = g_cb = g_cc = g_op = 0.0
            gcolor[:] = 0.0
            for py in range(by0, by1 + 1):
                dy = my - ys[py]
                lo, hi = _row_span(dy, mx, a, b, level, det, bx0, bx1)
                for px in range(lo, hi + 1):
                    i = (py - y0) * tw + (px - x0)
                    if kk >= last_local[i]:
                        continue
                    dx = mx - xs[px]
                    vis, raw, alpha = _alpha(dx, dy, a, b, c, opacity, consts)
                    if alpha == 0:
                        continue
                    alpha64 = np.float64(alpha)
                    inv_one_minus = 1.0 / (1.0 - alpha64)
                    t_before = trans[i] * inv_one_minus
                    trans[i] = t_before
                    weight = alpha64 * t_before
                    gc = 0.0
                    for d in range(n_dim):
                        gc += gcol[i, d] * rec[REC_COLORS + d]
                        gcolor[d] += weight * gcol[i, d]
                    grad_alpha = t_before * gc - (behind[i] + gq[i]) * inv_one_minus
                    behind[i] += weight * gc
                    if raw <= consts[1]:
                        grad_sigma = -np.float64(raw) * grad_alpha
                        g_op += np.float64(vis) * grad_alpha
                        dx64, dy64 = np.float64(dx), np.float64(dy)
                        gmx = grad_sigma * (a * dx64 + b * dy64)
                        gmy = grad_sigma * (b * dx64 + c * dy64)
                        g_mx += gmx
                        g_my += gmy
                        g_absx += abs(gmx)
                        g_absy += abs(gmy)
                        g_ca += 0.5 * grad_sigma * dx64 * dx64
                        g_cb += grad_sigma * dx64 * dy64
                        g_cc += 0.5 * grad_sigma * dy64 * dy64
            k = s + kk
            slots[k, 0], slots[k, 1], slots[k, 2], slots[k, 3] = g_mx, g_my, g_absx, g_absy
            slots[k, 4], slots[k, 5], slots[k, 6], slots[k, 7] = g_ca, g_cb, g_cc, g_op
            for d in range(n_dim):
                slots[k, N_GRAD + d] = gcolor[d]
    return slots


@njit(cache=True)
def _reduce_slots(slots, tile_items, n_records):
    """Sum the (tile, entry) slots per record, in slot order (deterministic)."""
    grads = np.zeros((n_records, slots.shape[1]), dtype=np.float64)
    for k in range(slots.shape[0]):
        j = tile_items[k]
        for col in range(slots.shape[1]):
            grads[j, col] += slots[k, col]
    return grads


def _balanced_tile_order(tile_start: np.ndarray) -> np.ndarray:
    """Non-empty tiles, ordered so that numba's static schedule (equal contiguous blocks of the
    ``prange`` per thread) gives every thread a similar share of list entries: sorted by entries,
    dealt round-robin. (numba's dynamic ``parallel_chunksize`` costs more than it saves here.)"""
    counts = np.diff(tile_start)
    order = np.argsort(-counts, kind="stable")
    order = order[: int(np.count_nonzero(counts))]
    n_threads = numba.get_num_threads()
    return np.concatenate([order[t::n_threads] for t in range(n_threads)])


_READY: Dict[torch.dtype, float] = {}

STAGE_SECONDS: Optional[Dict[str, float]] = None
"""When a dict (see :func:`profile_stages`), wall seconds per stage are added to it."""


@contextmanager
def profile_stages() -> Iterator[Dict[str, float]]:
    """Collect wall seconds per stage ("sort+bin", "forward kernel", "backward kernel",
    "reduce+scatter") of the renders inside the block (used by ``naka-gs-bench-raster``)."""
    global STAGE_SECONDS
    STAGE_SECONDS = {}
    try:
        yield STAGE_SECONDS
    finally:
        STAGE_SECONDS = None


@contextmanager
def _stage(name: str) -> Iterator[None]:
    if STAGE_SECONDS is None:
        yield
        return
    started = time.perf_counter()
    yield
    STAGE_SECONDS[name] = STAGE_SECONDS.get(name, 0.0) + time.perf_counter() - started


def warm_up(dtype: torch.dtype = torch.float32) -> float:
    """Compile (or load from numba's disk cache) every kernel for ``dtype``; returns the seconds
    taken and logs them once per dtype and process. Called by the first render of a dtype."""
    if dtype in _READY:
        return 0.0
    started = time.perf_counter()
    np_dtype = np.float32 if dtype == torch.float32 else np.float64
    boxes = np.array([[0, 1, 0, 1]], dtype=np.int64)
    tile_start, tile_items = _bin_tiles(boxes, np.zeros(1, dtype=np.int64), 1, 1, 1)
    centres = np.array([0.5, 1.5], dtype=np_dtype)
    records = np.array([[1.0, 1.0, 1.0, 0.0, 1.0, 0.5, 0.0, 1.0, 0.0, 1.0, 1.0, 1.0, 1.0]], dtype=np_dtype)
    consts = np.array([0.5, ALPHA_MAX, ALPHA_MIN, 0.0], dtype=np_dtype)
    args = (_balanced_tile_order(tile_start), tile_start, tile_items, records, centres, centres, consts, 1, 2, 2)
    _, t_final, last = _forward_kernel(*args)
    slots = _backward_kernel(*args, t_final, last, np.ones((4, 3)), np.ones(4))
    _reduce_slots(slots, tile_items, 1)
    seconds = time.perf_counter() - started
    kernels = (_bin_tiles, _forward_kernel, _backward_kernel, _reduce_slots)
    misses = sum(sum(k.stats.cache_misses.values()) for k in kernels)
    how = "compiled (and cached on disk)" if misses else "loaded from numba's disk cache"
    CONSOLE.log(
        f"[naka-gs] cpu-fast rasterizer: {dtype} kernels {how} in {seconds:.1f} s; {numba.get_num_threads()} threads",
        markup=False,
    )
    _READY[dtype] = seconds
    return seconds


class _TileComposite(torch.autograd.Function):
    """Front-to-back compositing over the tile lists; hand-written backward (see module docstring)."""

    @staticmethod
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
        warm_up(colors.dtype)
        n_cams, n, dim = colors.shape
        dtype = colors.dtype
        with _stage("sort+bin"):
            flat_opac = opacities.detach().reshape(-1)
            entries = torch.nonzero((radii.reshape(-1) > 0) & (flat_opac >= ALPHA_MIN)).squeeze(1)
            entries = entries.index_select(0, torch.argsort(depths.detach().reshape(-1)[entries], stable=True))
            boxes = pixel_bounds(means2d.detach(), radii, width, height).reshape(-1, 4).index_select(0, entries)
            # One record per visible entry, in depth order: every tile reads its list front to back
            # through memory in increasing address order.
            records = torch.cat(
                [
                    means2d.detach().reshape(-1, 2).index_select(0, entries),
                    conics.detach().reshape(-1, 3).index_select(0, entries),
                    flat_opac.index_select(0, entries)[:, None],
                    boxes.to(dtype),
                    colors.detach().reshape(-1, dim).index_select(0, entries),
                ],
                dim=1,
            ).numpy()
            tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
            tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
            cams = torch.div(entries, n, rounding_mode="floor")
            tile_start, tile_items = _bin_tiles(boxes.numpy(), cams.numpy(), n_cams, tiles_x, tiles_y)
            kernel_args = (
                _balanced_tile_order(tile_start),
                tile_start,
                tile_items,
                records,
                (torch.arange(width, dtype=dtype) + 0.5).numpy(),  # pixel centres, as the torch path
                (torch.arange(height, dtype=dtype) + 0.5).numpy(),
                np.array([0.5, ALPHA_MAX, ALPHA_MIN, 0.0], dtype=records.dtype),
                n_cams,
                width,
                height,
            )
        with _stage("forward kernel"):
            out, t_final, last = _forward_kernel(*kernel_args)
        out = torch.from_numpy(out)
        t_final_t = torch.from_numpy(t_final).to(dtype)
        if backgrounds is not None:
            out = out + (t_final_t.reshape(n_cams, -1, 1) * backgrounds[:, None, :].detach()).reshape(-1, dim)
        ctx.save_for_backward(means2d, backgrounds, entries)
        ctx.kernel_args = kernel_args + (t_final, last)
        ctx.meta = (n_cams, n, dim, absgrad)
        return out.reshape(n_cams, height, width, dim), (1.0 - t_final_t).reshape(n_cams, height, width, 1)

    @staticmethod
    def backward(ctx, grad_colors: Tensor, grad_alphas: Tensor):
        means2d, backgrounds, entries = ctx.saved_tensors
        n_cams, n, dim, absgrad = ctx.meta
        t_final = ctx.kernel_args[-2]
        dtype = grad_colors.dtype
        grad_colors = grad_colors.reshape(n_cams, -1, dim)
        upstream = -grad_alphas.reshape(n_cams, -1).double()
        if backgrounds is not None:
            upstream = upstream + (grad_colors * backgrounds[:, None, :]).sum(-1).double()
        grad_q = torch.from_numpy(t_final) * upstream.reshape(-1)
        with _stage("backward kernel"):
            slots = _backward_kernel(
                *ctx.kernel_args,
                grad_colors.reshape(-1, dim).double().contiguous().numpy(),
                grad_q.contiguous().numpy(),
            )
        with _stage("reduce+scatter"):
            per_record = torch.from_numpy(_reduce_slots(slots, ctx.kernel_args[2], len(entries))).to(dtype)
            grads = per_record.new_zeros(n_cams * n, N_GRAD + dim).index_copy_(0, entries, per_record)
        if absgrad:
            means2d.absgrad = grads[:, 2:4].reshape(n_cams, n, 2)
        grad_bg = None
        if backgrounds is not None and ctx.needs_input_grad[4]:
            t = torch.from_numpy(t_final).to(dtype).reshape(n_cams, -1, 1)
            grad_bg = (grad_colors * t).sum(1)
        return (
            grads[:, 0:2].reshape(n_cams, n, 2),
            grads[:, 4:7].reshape(n_cams, n, 3),
            grads[:, 7].reshape(n_cams, n),
            grads[:, N_GRAD:].reshape(n_cams, n, dim),
            grad_bg,
            None,
            None,
            None,
            None,
            None,
        )


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
    return _TileComposite.apply(means2d, conics, opacities, colors, backgrounds, depths, radii, width, height, absgrad)


def rasterization(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, " N"],
    colors: Tensor,
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
    and ``meta``) with the compiled compositing step; CPU tensors only."""
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
    )
