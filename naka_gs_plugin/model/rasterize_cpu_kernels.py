"""The cpu-fast rasterizer's compositing kernels (numba): forward, hand-written backward, per-Gaussian reduction.

They walk the tile lists of :mod:`~naka_gs_plugin.model.rasterize_cpu_lists`; the autograd function that runs them
is :class:`~naka_gs_plugin.model.rasterize_cpu_fast._TileComposite`.

Forward (``prange`` over tiles): front to back with ``alpha = min(0.999, opacity * exp(-sigma))``,
pairs with ``sigma < 0`` or ``alpha < 1/255`` skipped, a pixel stops *before* the pair that would
bring its transmittance to ``<= 1e-4``; transmittance is carried in float64 and the final
transmittance and the number of list entries up to the last contributing one are stored per pixel.
Backward (``prange`` over tiles): each pixel's list is walked back to front from that last entry,
recovering the transmittance by division (and reusing the ``exp(-sigma)`` the forward stored, one
per span pixel, up to ``VIS_STORE_MAX``), with the gradients for 2D means (and their per-pixel
absolute values, gsplat's ``absgrad``), conics, opacities and colours summed per (tile, list
entry) slot; a pass parallel over Gaussians (:func:`_reduce_slots`) then adds each one's slots up in
tile order, so there are no races and the result does not depend on the thread count.

In these generic kernels ``sigma`` and ``alpha`` are computed in the inputs' dtype,
operation for operation as the torch path (so the same pairs pass the 1/255 test, and the
backward re-derives exactly the forward's alphas); gradients accumulate in float64. No
``fastmath``: contraction into FMAs or approximate ``exp`` would let the forward, the backward and
the torch path disagree on pairs at the thresholds. They are the reference for the float32 RGB
kernels that training renders take when their row spans are wide enough (``RGB32_MIN_RUN``):
:func:`_forward_kernel_rgb32` and :func:`_backward_kernel_rgb32` evaluate 8 pixels of a tile row
as one vector, in float32 throughout (gsplat's CUDA precision) with a vectorisable ``exp``; both
derive bitwise the same alphas from each other, and agree with the generic kernels to float32
rounding.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

from naka_gs_plugin.model.rasterize import TILE_SIZE, TRANSMITTANCE_MIN
from naka_gs_plugin.model.rasterize_cpu_lists import REC_COLORS

N_GRAD = 8
"""Per-Gaussian gradient columns before the colours: d means2d (2), |d means2d| (2), d conics (3),
d opacity (1)."""


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
def _tile_box(tile, tiles_x, tiles_y, width, height):
    """``(camera, x0, y0, x1, y1)`` of a global tile index; ``x1``, ``y1`` exclusive."""
    cam = tile // (tiles_x * tiles_y)
    ty = (tile % (tiles_x * tiles_y)) // tiles_x
    x0, y0 = (tile % tiles_x) * TILE_SIZE, ty * TILE_SIZE
    return cam, x0, y0, min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)


@njit(parallel=True, cache=True)
def _forward_kernel(
    tile_order,
    tile_start,
    vis_start,
    slot_rows,
    slot_y,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    spans,
    vis_store,
):
    """Composite every tile; returns colours without background, T_final (f64) and last entries.
    Slot ``k``'s record has pixels in its tile on rows ``slot_y[k]`` (first, last); row ``py`` has the
    row span ``spans[slot_rows[k] + py]`` (see :func:`~naka_gs_plugin.model.rasterize_cpu_lists._row_spans`).
    Stores, for the backward to reuse instead of recomputing, the ``exp(-sigma)`` of every pair it
    evaluated (0 for skipped pairs) in ``vis_store``, slot ``k``'s span pixels from ``vis_start[k]`` on,
    row by row (unless it is shorter than ``vis_start[-1]``: then the backward recomputes them)."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_dim = records.shape[1] - REC_COLORS
    store_vis = vis_store.shape[0] >= vis_start[-1]
    # RGB (the training case) composites three scalars held in registers; the generic loop over
    # n_dim re-reads the record per pixel. Same sums in the same order: bitwise the generic result.
    rgb = n_dim == 3
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
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0 = np.float64(rec[REC_COLORS])
            c1 = np.float64(rec[REC_COLORS + min(1, n_dim - 1)])
            c2 = np.float64(rec[REC_COLORS + min(2, n_dim - 1)])
            by0, by1 = slot_y[k, 0], slot_y[k, 1]
            pos = vis_start[k]
            for py in range(by0, by1 + 1):
                lo = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                if lo > hi:
                    continue
                dy = my - ys[py]
                row_store = pos - lo
                pos += hi - lo + 1
                for px in range(lo, hi + 1):
                    i = (py - y0) * tw + (px - x0)
                    if done[i]:
                        continue
                    vis, _, alpha = _alpha(mx - xs[px], dy, a, b, c, opacity, consts)
                    if store_vis:
                        vis_store[row_store + px] = vis if alpha != 0 else consts[3]
                    if alpha == 0:
                        continue
                    t_next = trans[i] * (1.0 - np.float64(alpha))
                    if t_next <= TRANSMITTANCE_MIN:
                        done[i] = True
                        alive -= 1
                        continue
                    weight = np.float64(alpha) * trans[i]
                    if rgb:
                        acc[i, 0] += weight * c0
                        acc[i, 1] += weight * c1
                        acc[i, 2] += weight * c2
                    else:
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
    vis_start,
    slot_rows,
    slot_y,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    spans,
    t_final,
    last,
    vis_store,
    grad_colors,
    grad_q,
    slots,
):
    """Fill the per (tile, list entry) gradient ``slots`` [K, N_GRAD + D], walking each pixel back
    to front.

    ``grad_colors`` [P, D] is dL/d(colour without background) and ``grad_q`` [P] is
    ``T_final * (dL/dcolour . background - dL/dalpha)``: the upstream term every pair's
    transmittance derivative carries.
    """
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_dim = records.shape[1] - REC_COLORS
    store_vis = vis_store.shape[0] >= vis_start[-1]
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
        slots[s + k_end : tile_start[tile + 1]] = 0.0  # entries behind every pixel's last one
        for kk in range(k_end - 1, -1, -1):
            rec = records[s + kk]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            by0, by1 = slot_y[s + kk, 0], slot_y[s + kk, 1]
            rows = slot_rows[s + kk]
            pos = vis_start[s + kk]
            # Scalars (kept in registers) for the geometry, the colour part in a small array.
            g_mx = g_my = g_absx = g_absy = g_ca = g_cb = g_cc = g_op = 0.0
            gcolor[:] = 0.0
            for py in range(by0, by1 + 1):
                lo, hi = max(np.int64(spans[rows + py, 0]), x0), min(np.int64(spans[rows + py, 1]), x1 - 1)
                if lo > hi:
                    continue
                dy = my - ys[py]
                row_store = pos - lo
                pos += hi - lo + 1
                for px in range(lo, hi + 1):
                    i = (py - y0) * tw + (px - x0)
                    if kk >= last_local[i]:
                        continue
                    if store_vis:
                        # The forward evaluated this pair (the pixel was still compositing): its
                        # exp(-sigma), hence bitwise its alpha, or 0 where it skipped the pair.
                        vis = vis_store[row_store + px]
                        if vis == 0:
                            continue
                        raw = opacity * vis
                        alpha = min(raw, consts[1])
                    else:
                        vis, raw, alpha = _alpha(mx - xs[px], dy, a, b, c, opacity, consts)
                        if alpha == 0:
                            continue
                    dx = mx - xs[px]
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


LANES = 8
"""Pixels the float32 RGB kernels evaluate as one vector (AVX2's 8 float32 lanes): a tile row is
two such halves. Passed to the kernels at run time: a constant trip count gets the lane loop
unrolled, and LLVM does not vectorise the unrolled stores (they may alias). The kernels loop over
``lanes & -LANES``, a multiple of LANES to LLVM, which then emits no scalar remainder loop (and no
register shuffling between the two loops) after each vector."""

_PLANE = TILE_SIZE * TILE_SIZE


@intrinsic
def _bits_as_f32(typingctx, bits):
    """The float32 whose bits are the int32 ``bits`` (an LLVM bitcast, which vectorises)."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@njit(cache=True, inline="always")
def _exp_f32(x):
    """``exp(x)`` of a float32 ``x <= 0``, within 2 ulp (Cephes ``expf``; clamped at -80, where it
    is far below ``ALPHA_MIN``). Written out rather than ``np.exp``: libm's ``expf`` is a call LLVM
    cannot vectorise (no SVML here), and with no integer op wider than 32 bits its cost model picks
    8 lanes on AVX2."""
    half, one = np.float32(0.5), np.float32(1.0)
    x = max(x, np.float32(-80.0))
    n = np.float32(np.int32(x * np.float32(1.4426950408889634) - half))  # x <= 0: truncation rounds
    r = x - n * np.float32(0.693359375)
    r = r - n * np.float32(-2.12194440e-4)
    p = np.float32(1.9875691500e-4) * r + np.float32(1.3981999507e-3)
    p = p * r + np.float32(8.3334519073e-3)
    p = p * r + np.float32(4.1665795894e-2)
    p = p * r + np.float32(1.6666665459e-1)
    p = p * r + half
    p = p * (r * r) + r + one
    return p * _bits_as_f32(np.int32((n + np.float32(127.0)) * np.float32(8388608.0)))


@njit(cache=True)
def _sigma_vis_f32(dx, cdy, bdy, a):
    """``(sigma, exp(-sigma))`` of a pixel at ``dx`` in float32 (``exp(0)`` where ``sigma < 0``), with
    ``cdy = c * dy * dy`` and ``bdy = b * dy``. Not inlined by numba: LLVM inlines it after numba has
    set the backward's ``fastmath`` flags on the caller's own instructions only, so both float32
    kernels get bitwise the same alphas (the backward recovers the forward's transmittance)."""
    sigma = np.float32(0.5) * (a * dx * dx + cdy) + bdy * dx
    return sigma, _exp_f32(min(-sigma, np.float32(0.0)))


@njit(parallel=True, cache=True)
def _forward_kernel_rgb32(
    tile_order, tile_start, slot_rows, slot_y, records, xs, ys, consts, n_cams, width, height, spans, lanes
):
    """:func:`_forward_kernel` for float32 RGB, 8 pixels at a time: colours, T_final and last entries.

    Each row span's 8-pixel halves of its tile row are evaluated as one vector (``lanes`` = 8), every
    update a select on "inside the span, alpha passes, pixel still compositing"; transmittance is
    carried in float32 (gsplat's CUDA precision) and alpha comes from :func:`_exp_f32`, so results
    match the generic kernel's to float32 rounding (not bitwise). The tile's state lives in one array
    of 256-pixel planes (one base pointer: LLVM needs no runtime alias checks): transmittance, still
    compositing (1/0), r, g, b, last entry (small integers, exact), pixel centre x."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    alpha_max, alpha_min, t_min = consts[1], consts[2], np.float32(TRANSMITTANCE_MIN)
    out = np.zeros((n_cams * height * width, 3), dtype=np.float32)
    t_final = np.ones(n_cams * height * width, dtype=np.float32)
    last = np.zeros(n_cams * height * width, dtype=np.int32)
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        st = np.zeros(7 * _PLANE + LANES, dtype=np.float32)
        st[:_PLANE] = one
        for r in range(TILE_SIZE):
            for q in range(TILE_SIZE):
                st[_PLANE + r * TILE_SIZE + q] = one if r < y1 - y0 and q < tw else zero
                st[6 * _PLANE + r * TILE_SIZE + q] = np.float32(x0 + q) + half
        row_live = np.ones(TILE_SIZE, dtype=np.int64)
        for k in range(s, e):
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0, c1, c2 = rec[REC_COLORS], rec[REC_COLORS + 1], rec[REC_COLORS + 2]
            entry = np.float32(k - s + 1)
            for py in range(slot_y[k, 0], slot_y[k, 1] + 1):
                if row_live[py - y0] == 0:
                    continue
                lo_i = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi_i = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                if lo_i > hi_i:
                    continue
                lo, hi = xs[lo_i], xs[hi_i]
                dy = my - ys[py]
                cdy, bdy = c * dy * dy, b * dy
                for h in range((lo_i - x0) // LANES, (hi_i - x0) // LANES + 1):
                    v = st[(py - y0) * TILE_SIZE + h * LANES :]
                    for q in range(lanes & -LANES):
                        px = v[6 * _PLANE + q]
                        dx = mx - px
                        sigma, vis = _sigma_vis_f32(dx, cdy, bdy, a)
                        alpha = min(opacity * vis, alpha_max)
                        ok = (px >= lo) & (px <= hi) & (sigma >= zero) & (alpha >= alpha_min) & (v[_PLANE + q] > zero)
                        t = v[q]
                        t_next = t * (one - alpha)
                        stop = ok & (t_next <= t_min)
                        use = ok & (t_next > t_min)
                        w = alpha * t if use else zero
                        v[2 * _PLANE + q] += w * c0
                        v[3 * _PLANE + q] += w * c1
                        v[4 * _PLANE + q] += w * c2
                        v[q] = t_next if use else t
                        v[_PLANE + q] = zero if stop else v[_PLANE + q]
                        v[5 * _PLANE + q] = entry if use else v[5 * _PLANE + q]
            if (k - s) % 8 == 7:  # rows with no pixel left compositing are skipped from here on
                n_live = 0
                for r in range(TILE_SIZE):
                    row_live[r] = 1 if st[_PLANE + r * TILE_SIZE : _PLANE + (r + 1) * TILE_SIZE].max() > zero else 0
                    n_live += row_live[r]
                if n_live == 0:
                    break
        for i in range((y1 - y0) * tw):
            j = (i // tw) * TILE_SIZE + i % tw
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            out[p, 0], out[p, 1], out[p, 2] = st[2 * _PLANE + j], st[3 * _PLANE + j], st[4 * _PLANE + j]
            t_final[p] = st[j]
            last[p] = np.int32(st[5 * _PLANE + j])
    return out, t_final, last


@njit(cache=True, inline="always")
def _lane_sum(acc, row):
    """The sum of the 8 lanes ``acc[row * LANES : (row + 1) * LANES]``, pairwise."""
    o = row * LANES
    return ((acc[o] + acc[o + 1]) + (acc[o + 2] + acc[o + 3])) + ((acc[o + 4] + acc[o + 5]) + (acc[o + 6] + acc[o + 7]))


@njit(parallel=True, cache=True, fastmath={"reassoc", "nsz"})
def _backward_kernel_rgb32(
    tile_order,
    tile_start,
    slot_rows,
    slot_y,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    spans,
    lanes,
    t_final,
    last,
    grad_colors,
    grad_q,
    slots,
):
    """:func:`_backward_kernel` for float32 RGB from :func:`_forward_kernel_rgb32`'s ``t_final`` and
    ``last``: each pixel walked back to front, 8 pixels of a tile row at a time, alphas recomputed
    (nothing stored by the forward), float32 ``slots`` [K, N_GRAD + 3].

    An entry's gradient sums are kept per lane (``acc``, 11 rows of 8) over all its rows in the tile
    and added across the lanes once per entry (:func:`_lane_sum`): kept as scalars, LLVM reduces its
    8-wide partial sums after every half row, eleven horizontal sums per vector of pixels. Another
    summation order than the generic kernel's, fixed, so results do not depend on the thread count. The 8 pixels
    of a half row are skipped once the entry lies behind all their last entries. State planes:
    transmittance, the colour behind, last entry, upstream ``grad_q``, dL/dr, g, b, pixel centre x."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    alpha_max, alpha_min = consts[1], consts[2]
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        st = np.zeros(8 * _PLANE + LANES, dtype=np.float32)
        acc = np.zeros((N_GRAD + 3) * LANES, dtype=np.float32)  # slot columns x lanes
        half_last = np.zeros(2 * TILE_SIZE, dtype=np.int64)  # per 8 pixels of a tile row: their last entry
        k_end = 0
        for r in range(TILE_SIZE):
            for q in range(TILE_SIZE):
                j = r * TILE_SIZE + q
                st[7 * _PLANE + j] = np.float32(x0 + q) + half
                if r < y1 - y0 and q < tw:
                    p = (cam * height + y0 + r) * width + x0 + q
                    st[j] = t_final[p]
                    st[2 * _PLANE + j] = np.float32(last[p])
                    st[3 * _PLANE + j] = grad_q[p]
                    st[4 * _PLANE + j] = grad_colors[p, 0]
                    st[5 * _PLANE + j] = grad_colors[p, 1]
                    st[6 * _PLANE + j] = grad_colors[p, 2]
                    k_end = max(k_end, np.int64(last[p]))
                    half_last[r * 2 + q // LANES] = max(half_last[r * 2 + q // LANES], np.int64(last[p]))
        slots[s + k_end : e] = zero  # entries behind every pixel's last one
        for kk in range(k_end - 1, -1, -1):
            k = s + kk
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0, c1, c2 = rec[REC_COLORS], rec[REC_COLORS + 1], rec[REC_COLORS + 2]
            entry = np.float32(kk)
            acc[:] = zero
            for py in range(slot_y[k, 0], slot_y[k, 1] + 1):
                lo_i = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi_i = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                if lo_i > hi_i:
                    continue
                lo, hi = xs[lo_i], xs[hi_i]
                dy = my - ys[py]
                cdy, bdy = c * dy * dy, b * dy
                for h in range((lo_i - x0) // LANES, (hi_i - x0) // LANES + 1):
                    if kk >= half_last[(py - y0) * 2 + h]:
                        continue
                    v = st[(py - y0) * TILE_SIZE + h * LANES :]
                    for q in range(lanes & -LANES):
                        px = v[7 * _PLANE + q]
                        dx = mx - px
                        sigma, vis = _sigma_vis_f32(dx, cdy, bdy, a)
                        raw = opacity * vis
                        alpha = min(raw, alpha_max)
                        ok = (px >= lo) & (px <= hi) & (sigma >= zero) & (alpha >= alpha_min)
                        ok = ok & (v[2 * _PLANE + q] > entry)
                        inv = one / (one - alpha)
                        t_before = v[q] * inv
                        weight = alpha * t_before if ok else zero
                        gr, gg, gb = v[4 * _PLANE + q], v[5 * _PLANE + q], v[6 * _PLANE + q]
                        gc = gr * c0 + gg * c1 + gb * c2
                        behind = v[_PLANE + q]
                        grad_alpha = t_before * gc - (behind + v[3 * _PLANE + q]) * inv
                        v[q] = t_before if ok else v[q]
                        v[_PLANE + q] = behind + weight * gc
                        # alpha clamped at ALPHA_MAX: no gradient to the geometry or opacity.
                        ga = grad_alpha if ok & (raw <= alpha_max) else zero
                        gs = -raw * ga  # d/dsigma
                        gmx = gs * (a * dx + b * dy)
                        gmy = gs * (b * dx + c * dy)
                        acc[q] += gmx
                        acc[LANES + q] += gmy
                        acc[2 * LANES + q] += abs(gmx)
                        acc[3 * LANES + q] += abs(gmy)
                        acc[4 * LANES + q] += half * gs * dx * dx
                        acc[5 * LANES + q] += gs * dx * dy
                        acc[6 * LANES + q] += half * gs * dy * dy
                        acc[7 * LANES + q] += vis * ga
                        acc[N_GRAD * LANES + q] += weight * gr
                        acc[(N_GRAD + 1) * LANES + q] += weight * gg
                        acc[(N_GRAD + 2) * LANES + q] += weight * gb
            for col in range(N_GRAD + 3):
                slots[k, col] = _lane_sum(acc, col)


@njit(parallel=True, cache=True)
def _reduce_slots(slots, rec_start, rec_slots, entries, g_means2d, g_abs, g_conics, g_opac, g_colors):
    """Sum each record's (tile, entry) slots in increasing tile order (deterministic) into the
    zero-initialised per-entry gradients (flat [C*N, ...], the inputs' dtype; ``g_opac`` [C*N, 1])."""
    n_rec, n_cols = entries.shape[0], slots.shape[1]
    chunk = 256
    for first in prange((n_rec + chunk - 1) // chunk):
        acc = np.empty(n_cols)
        for j in range(first * chunk, min((first + 1) * chunk, n_rec)):
            acc[:] = 0.0
            for q in range(rec_start[j], rec_start[j + 1]):
                k = rec_slots[q]
                for col in range(n_cols):
                    acc[col] += slots[k, col]
            e = entries[j]
            g_means2d[e, 0], g_means2d[e, 1], g_abs[e, 0], g_abs[e, 1] = acc[0], acc[1], acc[2], acc[3]
            g_conics[e, 0], g_conics[e, 1], g_conics[e, 2], g_opac[e, 0] = acc[4], acc[5], acc[6], acc[7]
            for d in range(n_cols - N_GRAD):
                g_colors[e, d] = acc[N_GRAD + d]
