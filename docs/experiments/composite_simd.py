"""Compositing forward and backward vectorised 8 wide by LLVM, against the shipped ones (docs/cpu.md, "tenth profile").

Not used by the package: a measured lead. The shipped forward (``rasterize_cpu_fast._forward_kernel``) walks
each list entry's row span pixel by pixel in float32 alphas and float64 transmittance, skipping the pixels
already opaque. This one evaluates each span's 8-pixel halves of the tile row as whole vectors: float32
throughout, a float32 Cephes ``exp`` whose power of two is built by an LLVM bitcast (libm's ``expf`` call
cannot be vectorised without SVML), every update a select, and the tile's state in one array of 256-pixel
planes (one base pointer at constant distances: no runtime alias checks); the lane count is passed at run time
(a constant 8 is unrolled, and the unrolled stores are not vectorised). Results: the shipped forward's to float32
rounding (the same last entries; transmittance carried in float32 as gsplat's CUDA kernels do).

The backward (``backward_simd``) is in the same form: each pixel walked back to front 8 at a time from the
vectorised forward's float32 transmittance (``alpha`` recomputed, not stored), a list entry's gradient sums kept
as per-lane partial sums (``fastmath`` reassociation) and reduced once per half row, the 8 pixels of a half row
skipped once the entry is behind all of their last entries.

Captures the shipped forward's inputs for five training views of a trained run at 1/SCALE size (RGB), checks
the outputs against it and prints both kernels' wall, alternated, at the current numba thread count; then the
same for the two backwards under one seeded upstream gradient (gradient slots against the shipped kernel's,
relative to each column's largest). From the repository root (one thread: ``OMP_NUM_THREADS=1
NUMBA_NUM_THREADS=1 taskset -c 1``):

    .venv/bin/python docs/experiments/composite_simd.py CONFIG [--scale 2] [--repeats 7]
"""

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from llvmlite import ir
from nerfstudio.utils.eval_utils import eval_setup
from numba import njit, prange, types
from numba.extending import intrinsic

import naka_gs_plugin.model.rasterize_cpu_fast as raster_fast
from naka_gs_plugin.model.rasterize import TILE_SIZE, TRANSMITTANCE_MIN

F32 = np.float32
HALF, ONE, ZERO = F32(0.5), F32(1.0), F32(0.0)
LANES = 8
PLANES = 7  # transmittance, live (1/0), r, g, b, last entry (exact small integers), pixel centres x
PLANE = TILE_SIZE * TILE_SIZE
REC = raster_fast.REC_COLORS
N_GRAD = raster_fast.N_GRAD


@intrinsic
def _bits_as_f32(typingctx, bits):
    """The float32 whose bits are the int32 ``bits`` (an LLVM bitcast, which vectorises)."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@njit(inline="always")
def exp_f32(x):
    """``exp(x)`` for float32 ``x <= 0`` (Cephes ``expf``, within 2 ulp; clamped at -80). No integer op
    wider than 32 bits, so that LLVM's cost model picks 8 lanes on AVX2."""
    x = max(x, F32(-80.0))
    n = F32(np.int32(x * F32(1.4426950408889634) - HALF))  # x <= 0: truncation rounds to a nearest integer
    r = x - n * F32(0.693359375)
    r = r - n * F32(-2.12194440e-4)
    p = F32(1.9875691500e-4) * r + F32(1.3981999507e-3)
    p = ((((p * r + F32(8.3334519073e-3)) * r + F32(4.1665795894e-2)) * r + F32(1.6666665459e-1)) * r) + HALF
    p = p * (r * r) + r + ONE
    return p * _bits_as_f32(np.int32((n + F32(127.0)) * F32(8388608.0)))


@njit(parallel=True)
def forward_simd(
    tile_order, tile_start, slot_rows, slot_y, records, xs, ys, consts, n_cams, width, height, spans, lanes
):
    """The shipped forward's colours (RGB), final transmittance and last entries; ``lanes`` = 8."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    out = np.zeros((n_cams * height * width, 3), dtype=F32)
    t_final = np.ones(n_cams * height * width, dtype=F32)
    last = np.zeros(n_cams * height * width, dtype=np.int32)
    alpha_max, alpha_min, t_min = consts[1], consts[2], F32(TRANSMITTANCE_MIN)
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam = tile // (tiles_x * tiles_y)
        x0, y0 = (tile % tiles_x) * TILE_SIZE, ((tile % (tiles_x * tiles_y)) // tiles_x) * TILE_SIZE
        x1, y1 = min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)
        tw = x1 - x0
        st = np.zeros(PLANES * PLANE + LANES, dtype=F32)
        st[:PLANE] = ONE
        for r in range(TILE_SIZE):
            for q in range(TILE_SIZE):
                st[PLANE + r * TILE_SIZE + q] = ONE if r < y1 - y0 and q < tw else ZERO
                st[6 * PLANE + r * TILE_SIZE + q] = F32(x0 + q) + HALF
        row_live = np.ones(TILE_SIZE, dtype=np.int64)
        for k in range(s, e):
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0, c1, c2 = rec[REC], rec[REC + 1], rec[REC + 2]
            entry = F32(k - s + 1)
            for py in range(slot_y[k, 0], slot_y[k, 1] + 1):
                if row_live[py - y0] == 0:
                    continue
                lo_i = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi_i = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                lo, hi = F32(lo_i) + HALF, F32(hi_i) + HALF
                dy = my - ys[py]
                cdy, bdy = c * dy * dy, b * dy
                for h in range((lo_i - x0) // LANES, (hi_i - x0) // LANES + 1):
                    v = st[(py - y0) * TILE_SIZE + h * LANES :]
                    for q in range(lanes):
                        px = v[6 * PLANE + q]
                        dx = mx - px
                        sigma = HALF * (a * dx * dx + cdy) + bdy * dx
                        alpha = min(opacity * exp_f32(min(-sigma, ZERO)), alpha_max)
                        ok = (px >= lo) & (px <= hi) & (sigma >= ZERO) & (alpha >= alpha_min) & (v[PLANE + q] > ZERO)
                        t = v[q]
                        t_next = t * (ONE - alpha)
                        stop = ok & (t_next <= t_min)
                        use = ok & (t_next > t_min)
                        w = alpha * t if use else ZERO
                        v[2 * PLANE + q] += w * c0
                        v[3 * PLANE + q] += w * c1
                        v[4 * PLANE + q] += w * c2
                        v[q] = t_next if use else t
                        v[PLANE + q] = ZERO if stop else v[PLANE + q]
                        v[5 * PLANE + q] = entry if use else v[5 * PLANE + q]
            if (k - s) % 8 == 7:  # rows with no pixel left compositing are skipped from here on
                n_live = 0
                for r in range(TILE_SIZE):
                    row_live[r] = 1 if st[PLANE + r * TILE_SIZE : PLANE + (r + 1) * TILE_SIZE].max() > ZERO else 0
                    n_live += row_live[r]
                if n_live == 0:
                    break
        for i in range((y1 - y0) * tw):
            j = (i // tw) * TILE_SIZE + i % tw
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            out[p, 0], out[p, 1], out[p, 2] = st[2 * PLANE + j], st[3 * PLANE + j], st[4 * PLANE + j]
            t_final[p] = st[j]
            last[p] = np.int32(st[5 * PLANE + j])
    return out, t_final, last


BPLANES = 8  # transmittance, behind, last entry, upstream q, dL/dcolour r, g, b, pixel centres x


@njit(parallel=True, fastmath={"reassoc", "nsz"})
def backward_simd(
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
    t_final,
    last,
    grad_colors,
    grad_q,
    slots,
    lanes,
):
    """The shipped backward's gradient ``slots`` [K, N_GRAD + 3] (float32) from :func:`forward_simd`'s float32
    ``t_final`` and ``last``, each pixel walked back to front as there, 8 pixels of a tile row at a time.
    Each entry's sums are scalars the loop over lanes reduces: ``reassoc`` lets LLVM keep them as 8-wide
    partial sums and add the lanes once per half-row (another summation order than the shipped kernel's)."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    alpha_max, alpha_min = consts[1], consts[2]
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam = tile // (tiles_x * tiles_y)
        x0, y0 = (tile % tiles_x) * TILE_SIZE, ((tile % (tiles_x * tiles_y)) // tiles_x) * TILE_SIZE
        x1, y1 = min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)
        tw = x1 - x0
        st = np.zeros(BPLANES * PLANE + LANES, dtype=F32)
        half_last = np.zeros(2 * TILE_SIZE, dtype=np.int64)  # per 8 pixels of a row: their last entry
        k_end = 0
        for r in range(TILE_SIZE):
            for q in range(TILE_SIZE):
                j = r * TILE_SIZE + q
                st[7 * PLANE + j] = F32(x0 + q) + HALF
                if r < y1 - y0 and q < tw:
                    p = (cam * height + y0 + r) * width + x0 + q
                    st[j] = t_final[p]
                    st[2 * PLANE + j] = F32(last[p])
                    st[3 * PLANE + j] = grad_q[p]
                    st[4 * PLANE + j] = grad_colors[p, 0]
                    st[5 * PLANE + j] = grad_colors[p, 1]
                    st[6 * PLANE + j] = grad_colors[p, 2]
                    k_end = max(k_end, np.int64(last[p]))
                    half_last[r * 2 + q // LANES] = max(half_last[r * 2 + q // LANES], np.int64(last[p]))
        slots[s + k_end : e] = ZERO
        for kk in range(k_end - 1, -1, -1):
            k = s + kk
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0, c1, c2 = rec[REC], rec[REC + 1], rec[REC + 2]
            entry = F32(kk)
            g_mx = g_my = g_absx = g_absy = g_ca = g_cb = g_cc = g_op = g_r = g_g = g_b = ZERO
            for py in range(slot_y[k, 0], slot_y[k, 1] + 1):
                lo_i = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi_i = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                lo, hi = F32(lo_i) + HALF, F32(hi_i) + HALF
                dy = my - ys[py]
                cdy, bdy = c * dy * dy, b * dy
                for h in range((lo_i - x0) // LANES, (hi_i - x0) // LANES + 1):
                    if kk >= half_last[(py - y0) * 2 + h]:
                        continue
                    v = st[(py - y0) * TILE_SIZE + h * LANES :]
                    for q in range(lanes):
                        px = v[7 * PLANE + q]
                        dx = mx - px
                        sigma = HALF * (a * dx * dx + cdy) + bdy * dx
                        vis = exp_f32(min(-sigma, ZERO))
                        raw = opacity * vis
                        alpha = min(raw, alpha_max)
                        ok = (
                            (px >= lo)
                            & (px <= hi)
                            & (sigma >= ZERO)
                            & (alpha >= alpha_min)
                            & (v[2 * PLANE + q] > entry)
                        )
                        inv = ONE / (ONE - alpha)
                        t_before = v[q] * inv
                        weight = alpha * t_before if ok else ZERO
                        gr, gg, gb = v[4 * PLANE + q], v[5 * PLANE + q], v[6 * PLANE + q]
                        gc = gr * c0 + gg * c1 + gb * c2
                        behind = v[PLANE + q]
                        grad_alpha = t_before * gc - (behind + v[3 * PLANE + q]) * inv
                        v[q] = t_before if ok else v[q]
                        v[PLANE + q] = behind + weight * gc
                        g_r += weight * gr
                        g_g += weight * gg
                        g_b += weight * gb
                        geo = ok & (raw <= alpha_max)
                        ga = grad_alpha if geo else ZERO
                        gs = -raw * ga
                        g_op += vis * ga
                        gmx = gs * (a * dx + b * dy)
                        gmy = gs * (b * dx + c * dy)
                        g_mx += gmx
                        g_my += gmy
                        g_absx += abs(gmx)
                        g_absy += abs(gmy)
                        g_ca += HALF * gs * dx * dx
                        g_cb += gs * dx * dy
                        g_cc += HALF * gs * dy * dy
            slots[k, 0], slots[k, 1], slots[k, 2], slots[k, 3] = g_mx, g_my, g_absx, g_absy
            slots[k, 4], slots[k, 5], slots[k, 6], slots[k, 7] = g_ca, g_cb, g_cc, g_op
            slots[k, N_GRAD], slots[k, N_GRAD + 1], slots[k, N_GRAD + 2] = g_r, g_g, g_b


def captured_inputs(config: Path, scale: int) -> list:
    """The shipped forward kernel's arguments for five training views at 1/``scale`` size, RGB only."""
    _, pipeline, _, _ = eval_setup(config, test_mode="val")
    model = pipeline.model
    model.eval()
    model._get_downscale_factor = lambda: scale
    raster_fast.warm_up(torch.float32)
    shipped, calls = raster_fast._forward_kernel, []
    raster_fast._forward_kernel = lambda *args: (calls.append(args), shipped(*args))[1]
    cameras = pipeline.datamanager.train_dataset.cameras
    with torch.no_grad():
        for i in range(0, len(cameras), max(1, len(cameras) // 5))[:5]:
            model.get_outputs(cameras[i : i + 1])
    raster_fast._forward_kernel = shipped
    rgb = raster_fast.REC_COLORS + 3  # eval renders RGB+depth; training composites RGB
    return [args[:5] + (np.ascontiguousarray(args[5][:, :rgb]),) + args[6:] for args in calls]


def alternated(*kernels, repeats: int) -> list:
    """Median seconds of each ``(kernel, [args, ...])`` over all its calls, the kernels taking turns and the
    order reversed every other repeat (this VM's speed drifts)."""
    seconds = [[] for _ in kernels]
    for repeat in range(repeats):
        order = list(enumerate(kernels))
        for i, (kernel, inputs) in order if repeat % 2 == 0 else order[::-1]:
            started = time.perf_counter()
            for kernel_args in inputs:
                kernel(*kernel_args)
            seconds[i].append(time.perf_counter() - started)
    return [float(np.median(s)) for s in seconds]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--scale", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    shipped_args = captured_inputs(args.config, args.scale)
    simd_args = []
    for tile_order, tile_start, _, slot_rows, slot_y, records, xs, ys, consts, n_cams, w, h, spans, _ in shipped_args:
        simd_args.append(
            (tile_order, tile_start, slot_rows, slot_y, records, xs, ys, consts, n_cams, w, h, spans, LANES)
        )
    for a, b in zip(shipped_args, simd_args):
        (out_a, t_a, last_a), (out_b, t_b, last_b) = raster_fast._forward_kernel(*a), forward_simd(*b)
        print(
            f"max |colour difference| {np.abs(out_a - out_b).max():.2e}, transmittance {np.abs(t_a - t_b).max():.2e}, "
            f"last entries differing {(last_a != last_b).mean():.2%}"
        )
    shipped, simd = alternated(
        (raster_fast._forward_kernel, shipped_args), (forward_simd, simd_args), repeats=args.repeats
    )
    print(
        f"1/{args.scale} size, {len(shipped_args)} views: shipped forward {1000 * shipped:.1f} ms, "
        f"vectorised {1000 * simd:.1f} ms (x{simd / shipped:.2f})"
    )
    # Backward: each kernel from its own forward's outputs, one seeded upstream gradient per view.
    rng = np.random.default_rng(0)
    shipped_bwd, simd_bwd = [], []
    for a, b in zip(shipped_args, simd_args):
        vis_start, n_cams, w, h = a[2], a[9], a[10], a[11]
        vis_store = np.zeros(int(vis_start[-1]), dtype=F32)
        _, t64, last64 = raster_fast._forward_kernel(*a[:13], vis_store)
        _, t32, last32 = forward_simd(*b)
        grad_colors = rng.normal(size=(n_cams * h * w, 3))
        upstream = 0.1 * rng.normal(size=n_cams * h * w)
        n_slots = a[5].shape[0]
        shipped_bwd.append(
            a[:13] + (t64, last64, vis_store, grad_colors, t64 * upstream, np.zeros((n_slots, N_GRAD + 3)))
        )
        simd_bwd.append(
            b[:12]
            + (
                t32,
                last32,
                grad_colors.astype(F32),
                (t32 * upstream).astype(F32),
                np.zeros((n_slots, N_GRAD + 3), F32),
                LANES,
            )
        )
    for a, b in zip(shipped_bwd, simd_bwd):
        raster_fast._backward_kernel(*a)
        backward_simd(*b)
        ref, got = a[-1], b[-2]
        scale = np.abs(ref).max(axis=0)
        print(
            "max |slot difference| / column max:", " ".join(f"{x:.1e}" for x in np.abs(ref - got).max(axis=0) / scale)
        )
    shipped_b, simd_b = alternated(
        (raster_fast._backward_kernel, shipped_bwd), (backward_simd, simd_bwd), repeats=args.repeats
    )
    print(
        f"1/{args.scale} size, {len(shipped_args)} views: shipped backward {1000 * shipped_b:.1f} ms, "
        f"vectorised {1000 * simd_b:.1f} ms (x{simd_b / shipped_b:.2f}); forward + backward "
        f"x{(simd + simd_b) / (shipped + shipped_b):.2f}"
    )


if __name__ == "__main__":
    main()
