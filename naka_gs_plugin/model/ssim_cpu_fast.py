"""Compiled CPU SSIM: numba kernels with a hand-written backward (the fast path of :mod:`.ssim`).

The same maths as ``pytorch_msssim`` (the readable reference beside it, which :class:`.ssim.SSIMLoss` runs
everywhere else): the five moments ``x, y, x^2, y^2, xy`` blurred by the separable window over the valid region,
vertically then horizontally, in one pass over the output rows (``prange``), which also evaluates the SSIM map and
its derivatives with respect to one input's blurred mean, blurred square and the blurred product; the backward is
two transposed blurs of those three maps. Images are (H, W*C) float32 rows of interleaved channels (HWC memory, as
splatfacto's images are), arithmetic is float32 as the reference's (sums over the window in another order), each
row's sum of the map is float64. Every output row is computed by one thread alone, so the results do not depend
on the thread count. No ``fastmath``. Kernels compile on first use and are cached on disk by numba (as
:mod:`.rasterize_cpu_fast`'s).
"""

from __future__ import annotations

import numpy as np
import torch
from jaxtyping import Float
from numba import njit, prange
from torch import Tensor

# Every loop below updates one array from others with plain indices: numba vectorises those, not a loop that
# updates several arrays, indexes a shifted window (v[q + shift]: the kernels take slices instead) or mixes in
# numba's float64 literals.


@njit(cache=True, inline="always")
def _add_scaled(dst, w, src):
    """dst += w * src."""
    for q in range(dst.shape[0]):
        dst[q] += w * src[q]


@njit(cache=True, inline="always")
def _add_scaled_product(dst, w, a, b):
    """dst += w * a * b."""
    for q in range(dst.shape[0]):
        dst[q] += w * (a[q] * b[q])


@njit(cache=True, inline="always")
def _ssim_terms(mx, my, exx, eyy, exy, c1, c2):
    """``(2 mx my + C1, mx^2 + my^2 + C1, 2 sxy + C2, sxx + syy + C2)`` from the blurred moments."""
    two = np.float32(2.0)
    return (
        two * mx * my + c1,
        mx * mx + my * my + c1,
        two * (exy - mx * my) + c2,
        (exx - mx * mx) + (eyy - my * my) + c2,
    )


@njit(parallel=True, cache=True)
def _forward_kernel(x, y, g, channels, c1, c2, want_grad, row_sums, p_m, p_e, p_c):
    """x, y: (H, W*C); g: (K,) window. Fills ``row_sums[i]`` with the sum of the SSIM map over output row i and,
    if ``want_grad``, the map's derivatives with respect to x's blurred mean (p_m), x's blurred square (p_e) and
    the blurred product (p_c), each (H-K+1, (W-K+1)*C)."""
    two = np.float32(2.0)
    c1 = np.float32(c1)
    c2 = np.float32(c2)
    taps = g.shape[0]
    out_rows = x.shape[0] - taps + 1
    width = x.shape[1]
    out_width = width - (taps - 1) * channels
    for i in prange(out_rows):
        v = np.zeros((5, width), np.float32)
        for t in range(taps):
            a, b = x[i + t], y[i + t]
            _add_scaled(v[0], g[t], a)
            _add_scaled(v[1], g[t], b)
            _add_scaled_product(v[2], g[t], a, a)
            _add_scaled_product(v[3], g[t], b, b)
            _add_scaled_product(v[4], g[t], a, b)
        h = np.zeros((5, out_width), np.float32)
        for t in range(taps):
            lo = t * channels
            for k in range(5):
                _add_scaled(h[k], g[t], v[k, lo : lo + out_width])
        mx, my, exx, eyy, exy = h[0], h[1], h[2], h[3], h[4]
        value = np.empty(out_width, np.float32)
        if want_grad:
            for q in range(out_width):
                a1, a2, b1, b2 = _ssim_terms(mx[q], my[q], exx[q], eyy[q], exy[q], c1, c2)
                lum = a1 / a2
                cs = b1 / b2
                value[q] = lum * cs
                p_m[i, q] = two * (
                    cs * (my[q] * a2 - a1 * mx[q]) / (a2 * a2) + lum * (b1 * mx[q] - my[q] * b2) / (b2 * b2)
                )
                p_e[i, q] = -lum * b1 / (b2 * b2)
                p_c[i, q] = two * lum / b2
        else:
            for q in range(out_width):
                a1, a2, b1, b2 = _ssim_terms(mx[q], my[q], exx[q], eyy[q], exy[q], c1, c2)
                value[q] = (a1 / a2) * (b1 / b2)
        total = 0.0
        for q in range(out_width):
            total += value[q]
        row_sums[i] = total


@njit(parallel=True, cache=True)
def _backward_kernel(x, y, g, channels, p_m, p_e, p_c, scale, grad_x):
    """grad_x (H, W*C) = scale * (G^T p_m + 2 x G^T p_e + y G^T p_c), G the valid separable blur."""
    two = np.float32(2.0)
    scale = np.float32(scale)
    taps = g.shape[0]
    out_rows, out_width = p_m.shape
    rows, width = x.shape
    spread = np.zeros((3, out_rows, width), np.float32)
    for o in prange(out_rows):
        for t in range(taps):
            lo = t * channels
            _add_scaled(spread[0, o, lo : lo + out_width], g[t], p_m[o])
            _add_scaled(spread[1, o, lo : lo + out_width], g[t], p_e[o])
            _add_scaled(spread[2, o, lo : lo + out_width], g[t], p_c[o])
    for r in prange(rows):
        acc = np.zeros((3, width), np.float32)
        for t in range(max(0, r - out_rows + 1), min(taps, r + 1)):
            for k in range(3):
                _add_scaled(acc[k], g[t], spread[k, r - t])
        xr, yr, out = x[r], y[r], grad_x[r]
        for q in range(width):
            out[q] = scale * (acc[0, q] + two * xr[q] * acc[1, q] + yr[q] * acc[2, q])


def _rows(image: Float[Tensor, "C H W"]) -> np.ndarray:
    """(H, W*C) float32 rows of interleaved channels (a view when the image is a permuted HWC tensor)."""
    return np.ascontiguousarray(image.detach().permute(1, 2, 0).reshape(image.shape[1], -1).numpy())


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, X: Tensor, Y: Tensor, window: np.ndarray, c1: float, c2: float) -> Tensor:
        n, channels, height, width = X.shape
        taps = window.shape[0]
        out_shape = (height - taps + 1, (width - taps + 1) * channels)
        grads = [i for i, need in enumerate(ctx.needs_input_grad[:2]) if need]
        total = 0.0
        saved = []
        for b in range(n):
            x, y = _rows(X[b]), _rows(Y[b])
            row_sums = np.empty(out_shape[0], np.float64)
            partials = []
            for which in grads:  # the SSIM map is symmetric: Y's derivatives are X's with the two swapped
                maps = [np.empty(out_shape, np.float32) for _ in range(3)]
                first, second = (x, y) if which == 0 else (y, x)
                _forward_kernel(first, second, window, channels, c1, c2, True, row_sums, *maps)
                partials.append(maps)
            if not grads:
                unused = np.empty((1, 1), np.float32)
                _forward_kernel(x, y, window, channels, c1, c2, False, row_sums, unused, unused, unused)
            total += float(row_sums.sum())
            saved.append((x, y, partials))
        ctx.saved = saved
        ctx.window, ctx.grads, ctx.shape = window, grads, X.shape
        ctx.count = n * channels * (height - taps + 1) * (width - taps + 1)
        return X.new_tensor(total / ctx.count)

    @staticmethod
    def backward(ctx, grad_output: Tensor):
        n, channels, height, width = ctx.shape
        scale = float(grad_output) / ctx.count
        out = [None, None]
        for which in ctx.grads:
            grad = torch.empty(n, height, width, channels, dtype=torch.float32)
            for b, (x, y, partials) in enumerate(ctx.saved):
                first, second = (x, y) if which == 0 else (y, x)
                maps = partials[ctx.grads.index(which)]
                _backward_kernel(first, second, ctx.window, channels, *maps, scale, grad[b].view(height, -1).numpy())
            out[which] = grad.permute(0, 3, 1, 2)
        ctx.saved = None
        return out[0], out[1], None, None, None


def ssim_cpu_fast(
    X: Float[Tensor, "N C H W"], Y: Float[Tensor, "N C H W"], window: Float[np.ndarray, " K"], c1: float, c2: float
) -> Tensor:
    """Mean SSIM of float32 CPU images (H, W >= K) with the 1D ``window``, ``C1 = c1``, ``C2 = c2``; differentiable
    in whichever inputs require a gradient."""
    return _FusedSSIM.apply(X, Y, window, c1, c2)
