"""Compiled CPU SSIM: numba kernels with a hand-written backward (the fast path of :mod:`.ssim`).

The same maths as ``pytorch_msssim`` (the readable reference beside it, which :class:`.ssim.SSIMLoss` runs
everywhere else): the five moments ``x, y, x^2, y^2, xy`` blurred by the separable window over the valid region,
vertically then horizontally, in one pass over the output rows (``prange``), which also evaluates the SSIM map and
its derivatives with respect to one input's blurred mean, blurred square and the blurred product; the backward is
two transposed blurs of those three maps. Images are (H, W*C) float32 rows of interleaved channels (HWC memory, as
splatfacto's images are), arithmetic is float32 as the reference's (sums over the window in another order), each
row's sum of the map is float64. The window's length and the channel count are compile-time constants
(:data:`TAPS`, :data:`CHANNELS`: splatfacto's 11 taps and RGB), so the taps unroll. Every output row is computed by one thread alone, so the results do not depend
on the thread count. No ``fastmath`` but in :func:`_error_kernel`'s sums. Kernels compile on first use and are cached on disk by numba (as
:mod:`.rasterize_cpu_fast`'s).
"""

from __future__ import annotations

import numpy as np
import torch
from jaxtyping import Float
from numba import njit, prange
from torch import Tensor

from naka_gs_plugin.cpu import untraced
from naka_gs_plugin.model.ssim import FAST_CHANNELS, FAST_TAPS

TAPS = FAST_TAPS  # numba compiles module globals as constants
CHANNELS = FAST_CHANNELS

# Every loop below runs over one row's columns with the window's taps unrolled inside it (TAPS and CHANNELS are
# constants), so LLVM vectorises the columns and keeps the taps' sums in registers. It does so only where every
# index is provably non-negative (the taps are offsets from a row or column that is), where the row's sum is taken
# in a loop of its own (a float64 sum across float32 lanes is not reassociated without fastmath) and where the
# arrays read are C-contiguous 2D or 1D arrays (a slice of a 3D array is not).


@njit(parallel=True, cache=True)
def _forward_kernel(x, y, g, c1, c2, want_grad, row_sums, p_m, p_e, p_c):
    """x, y: (H, W*C); g: (TAPS,) window. Fills ``row_sums[i]`` with the sum of the SSIM map over output row i and,
    if ``want_grad``, the map's derivatives with respect to x's blurred mean (p_m), x's blurred square (p_e) and
    the blurred product (p_c), each (H-K+1, (W-K+1)*C)."""
    two = np.float32(2.0)
    zero = np.float32(0.0)
    c1 = np.float32(c1)
    c2 = np.float32(c2)
    out_rows = x.shape[0] - TAPS + 1
    width = x.shape[1]
    out_width = width - (TAPS - 1) * CHANNELS
    for i in prange(out_rows):
        # Vertical blur of the five moments x, y, x^2, y^2, xy.
        v0 = np.empty(width, np.float32)
        v1 = np.empty(width, np.float32)
        v2 = np.empty(width, np.float32)
        v3 = np.empty(width, np.float32)
        v4 = np.empty(width, np.float32)
        for q in range(width):
            s0, s1, s2, s3, s4 = zero, zero, zero, zero, zero
            for t in range(TAPS):
                a, b, w = x[i + t, q], y[i + t, q], g[t]
                s0 += w * a
                s1 += w * b
                s2 += w * (a * a)
                s3 += w * (b * b)
                s4 += w * (a * b)
            v0[q], v1[q], v2[q], v3[q], v4[q] = s0, s1, s2, s3, s4
        # Horizontal blur, the SSIM map and its partial derivatives.
        value = np.empty(out_width, np.float32)
        for q in range(out_width):
            mx, my, exx, eyy, exy = zero, zero, zero, zero, zero
            for t in range(TAPS):
                w, k = g[t], q + t * CHANNELS
                mx += w * v0[k]
                my += w * v1[k]
                exx += w * v2[k]
                eyy += w * v3[k]
                exy += w * v4[k]
            a1 = two * mx * my + c1
            a2 = mx * mx + my * my + c1
            b1 = two * (exy - mx * my) + c2
            b2 = (exx - mx * mx) + (eyy - my * my) + c2
            lum = a1 / a2
            cs = b1 / b2
            value[q] = lum * cs
            if want_grad:
                p_m[i, q] = two * (cs * (my * a2 - a1 * mx) / (a2 * a2) + lum * (b1 * mx - my * b2) / (b2 * b2))
                p_e[i, q] = -lum * b1 / (b2 * b2)
                p_c[i, q] = two * lum / b2
        total = 0.0
        for q in range(out_width):
            total += value[q]
        row_sums[i] = total


@njit(cache=True, inline="always")
def _spread_at(q, g, m, e, c, s0, s1, s2):
    """Column q of the transposed horizontal blur of the three map rows, the taps that fall outside skipped."""
    zero = np.float32(0.0)
    a0, a1, a2 = zero, zero, zero
    for t in range(TAPS):
        k = q - t * CHANNELS
        if 0 <= k < m.shape[0]:
            w = g[t]
            a0 += w * m[k]
            a1 += w * e[k]
            a2 += w * c[k]
    s0[q], s1[q], s2[q] = a0, a1, a2


@njit(parallel=True, cache=True, fastmath={"reassoc"})
def _error_kernel(x, y, abs_rows, square_rows):
    """x, y: (H, W*C). Fills ``abs_rows[r]`` and ``square_rows[r]`` with the sums of |x - y| and (x - y)^2 over row
    r, in float64. The one fast-math flag, ``reassoc``, lets LLVM sum a row in vector lanes (a quarter of the time of
    one sequential sum); NaN and infinities still propagate, and the order of the sums is fixed at compile time, so
    the bits do not depend on the thread count (only, in the last place, on the CPU's vector width)."""
    for r in prange(x.shape[0]):
        xr, yr = x[r], y[r]
        total, squares = 0.0, 0.0
        for q in range(x.shape[1]):
            d = np.float64(xr[q]) - np.float64(yr[q])
            total += abs(d)
            squares += d * d
        abs_rows[r] = total
        square_rows[r] = squares


@njit(parallel=True, cache=True)
def _backward_kernel(x, y, g, p_m, p_e, p_c, scale, l1_scale, grad_x):
    """grad_x (H, W*C) = scale * (G^T p_m + 2 x G^T p_e + y G^T p_c) + l1_scale * sign(x - y), G the valid separable
    blur: the transposed horizontal blur of each map row, then the transposed vertical blur, each as a gather over
    the taps; the last term is the gradient of an L1 term (sign(0) = 0, as torch's)."""
    two = np.float32(2.0)
    zero = np.float32(0.0)
    scale = np.float32(scale)
    l1_scale = np.float32(l1_scale)
    out_rows, out_width = p_m.shape
    rows, width = x.shape
    edge = (TAPS - 1) * CHANNELS
    sp0 = np.empty((out_rows, width), np.float32)
    sp1 = np.empty((out_rows, width), np.float32)
    sp2 = np.empty((out_rows, width), np.float32)
    for o in prange(out_rows):
        m, e, c = p_m[o], p_e[o], p_c[o]
        s0, s1, s2 = sp0[o, edge:], sp1[o, edge:], sp2[o, edge:]
        for q in range(out_width - edge):  # column q + edge, all of whose taps fall inside the map
            a0, a1, a2 = zero, zero, zero
            for t in range(TAPS):
                w, k = g[t], q + (TAPS - 1 - t) * CHANNELS
                a0 += w * m[k]
                a1 += w * e[k]
                a2 += w * c[k]
            s0[q], s1[q], s2[q] = a0, a1, a2
        for q in range(min(edge, width)):
            _spread_at(q, g, m, e, c, sp0[o], sp1[o], sp2[o])
        for q in range(max(out_width, edge), width):
            _spread_at(q, g, m, e, c, sp0[o], sp1[o], sp2[o])
    for r in prange(rows):
        xr, yr, out = x[r], y[r], grad_x[r]
        if TAPS - 1 <= r < out_rows:  # all taps inside the maps: rows base .. base + TAPS - 1
            base = r - (TAPS - 1)
            for q in range(width):
                a0, a1, a2 = zero, zero, zero
                for t in range(TAPS):
                    w, j = g[t], base + TAPS - 1 - t
                    a0 += w * sp0[j, q]
                    a1 += w * sp1[j, q]
                    a2 += w * sp2[j, q]
                d = xr[q] - yr[q]
                out[q] = scale * (a0 + two * xr[q] * a1 + yr[q] * a2) + l1_scale * (
                    np.float32(d > zero) - np.float32(d < zero)
                )
        else:
            lo, hi = max(0, r - out_rows + 1), min(TAPS, r + 1)
            for q in range(width):
                a0, a1, a2 = zero, zero, zero
                for t in range(lo, hi):
                    w = g[t]
                    a0 += w * sp0[r - t, q]
                    a1 += w * sp1[r - t, q]
                    a2 += w * sp2[r - t, q]
                d = xr[q] - yr[q]
                out[q] = scale * (a0 + two * xr[q] * a1 + yr[q] * a2) + l1_scale * (
                    np.float32(d > zero) - np.float32(d < zero)
                )


def _rows(image: Float[Tensor, "C H W"]) -> np.ndarray:
    """(H, W*C) float32 rows of interleaved channels (a view when the image is a permuted HWC tensor)."""
    return np.ascontiguousarray(image.detach().permute(1, 2, 0).reshape(image.shape[1], -1).numpy())


@untraced()
def error_sums(a: Float[Tensor, "*shape"], b: Float[Tensor, "*shape"]) -> tuple:
    """Sums of |a - b| and (a - b)^2 over every element of two float32 CPU tensors of one shape (at least 1D), as
    Python floats: float64 arithmetic, the same bits with any thread count. Contiguous tensors are read in place."""
    x = np.ascontiguousarray(a.detach().reshape(a.shape[0] if a.dim() > 1 else 1, -1).numpy())
    y = np.ascontiguousarray(b.detach().reshape(x.shape).numpy())
    abs_rows, square_rows = np.empty(x.shape[0], np.float64), np.empty(x.shape[0], np.float64)
    _error_kernel(x, y, abs_rows, square_rows)
    return float(abs_rows.sum()), float(square_rows.sum())


class _FusedSSIM(torch.autograd.Function):
    """``ssim_weight * SSIM(X, Y) + l1_weight * mean|X - Y|``: the L1 term's value from one more pass over the
    images, its gradient inside the SSIM's backward kernel (no pass of its own)."""

    @staticmethod
    @untraced()
    def forward(
        ctx, X: Tensor, Y: Tensor, window: np.ndarray, c1: float, c2: float, ssim_weight: float, l1_weight: float
    ) -> Tensor:
        n, channels, height, width = X.shape
        taps = window.shape[0]
        out_shape = (height - taps + 1, (width - taps + 1) * channels)
        grads = [i for i, need in enumerate(ctx.needs_input_grad[:2]) if need]
        total, abs_total = 0.0, 0.0
        saved = []
        for b in range(n):
            x, y = _rows(X[b]), _rows(Y[b])
            row_sums = np.empty(out_shape[0], np.float64)
            partials = []
            for which in grads:  # the SSIM map is symmetric: Y's derivatives are X's with the two swapped
                maps = [np.empty(out_shape, np.float32) for _ in range(3)]
                first, second = (x, y) if which == 0 else (y, x)
                _forward_kernel(first, second, window, c1, c2, True, row_sums, *maps)
                partials.append(maps)
            if not grads:
                unused = np.empty((1, 1), np.float32)
                _forward_kernel(x, y, window, c1, c2, False, row_sums, unused, unused, unused)
            total += float(row_sums.sum())
            if l1_weight:
                abs_rows, square_rows = np.empty(height, np.float64), np.empty(height, np.float64)
                _error_kernel(x, y, abs_rows, square_rows)
                abs_total += float(abs_rows.sum())
            saved.append((x, y, partials))
        ctx.saved = saved
        ctx.window, ctx.grads, ctx.shape, ctx.weights = window, grads, X.shape, (ssim_weight, l1_weight)
        ctx.count = n * channels * (height - taps + 1) * (width - taps + 1)
        return X.new_tensor(ssim_weight * total / ctx.count + l1_weight * abs_total / X.numel())

    @staticmethod
    @untraced()
    def backward(ctx, grad_output: Tensor):
        n, channels, height, width = ctx.shape
        ssim_weight, l1_weight = ctx.weights
        scale = float(grad_output) * ssim_weight / ctx.count
        l1_scale = float(grad_output) * l1_weight / (n * channels * height * width)
        out = [None, None]
        for which in ctx.grads:
            grad = torch.empty(n, height, width, channels, dtype=torch.float32)
            for b, (x, y, partials) in enumerate(ctx.saved):
                first, second = (x, y) if which == 0 else (y, x)
                maps = partials[ctx.grads.index(which)]
                _backward_kernel(first, second, ctx.window, *maps, scale, l1_scale, grad[b].view(height, -1).numpy())
            out[which] = grad.permute(0, 3, 1, 2)
        ctx.saved = None
        return out[0], out[1], None, None, None, None, None


def ssim_cpu_fast(
    X: Float[Tensor, "N C H W"], Y: Float[Tensor, "N C H W"], window: Float[np.ndarray, " K"], c1: float, c2: float
) -> Tensor:
    """Mean SSIM of float32 CPU images with :data:`CHANNELS` channels (H, W >= :data:`TAPS`) with the 1D ``window``
    of :data:`TAPS` taps, ``C1 = c1``, ``C2 = c2``; differentiable in whichever inputs require a gradient."""
    return _FusedSSIM.apply(X, Y, window, c1, c2, 1.0, 0.0)


def l1_ssim_loss_cpu_fast(
    X: Float[Tensor, "N C H W"],
    Y: Float[Tensor, "N C H W"],
    window: Float[np.ndarray, " K"],
    c1: float,
    c2: float,
    ssim_lambda: float,
) -> Tensor:
    """Splatfacto's training loss ``(1 - ssim_lambda) * mean|X - Y| + ssim_lambda * (1 - SSIM(X, Y))`` of the images
    :func:`ssim_cpu_fast` takes, in one autograd node: the L1 term's gradient is added inside the SSIM's backward."""
    return ssim_lambda + _FusedSSIM.apply(X, Y, window, c1, c2, -ssim_lambda, 1.0 - ssim_lambda)
