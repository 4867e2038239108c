"""Splatfacto's SSIM loss as two compiled CPU kernels, forward and a hand-written backward.

Splatfacto scores every training step with ``pytorch_msssim.SSIM(data_range=1, channel=3)``: an 11-tap
Gaussian window (sigma 1.5) over the valid region (no padding), ``K = (0.01, 0.03)``, the mean of the SSIM
map over batch, channels and pixels. On a CPU that module is five grouped ``conv2d`` pairs forward and as
many in autograd's backward, plus a dozen full-size temporaries: at 500x375 it costs more than the
rasterizer does at a few thousand Gaussians. :class:`SSIMLoss` is that module (same constructor, same
attributes, used for the eval metric too) whose ``forward`` runs, for float32 CPU images of at least
11x11 pixels when numba imports, the same maths as one pass over the image rows (the five moments blurred
vertically then horizontally, the SSIM map and its derivatives with respect to the blurred moments) and a
backward of two transposed blurs of three maps. Anything else (CUDA, float64, tiny images) runs
``pytorch_msssim``, which is also the readable reference the tests compare with.

Inputs are NCHW in [0, 1] (any strides: splatfacto passes permuted HWC images); SSIM is symmetric, so
whichever of the two inputs requires a gradient gets it. Arithmetic is float32 as the reference's (sums
over the window in a different order: results agree to float32 rounding); the mean is summed in float64.
No ``fastmath``, so results do not depend on the CPU's vector width beyond that.
"""

from __future__ import annotations

import numpy as np
import torch
from jaxtyping import Float
from pytorch_msssim import SSIM
from torch import Tensor

try:
    from numba import njit, prange
except ImportError:  # numba is a dependency, but a broken install only loses the fast path
    njit = None


def _fused_kernels():
    """The forward and backward kernels, compiled on first use (and cached on disk by numba)."""

    @njit(parallel=True, cache=True)
    def forward(x, y, g, channels, c1, c2, want_grad, row_sums, p_m, p_e, p_c):
        """x, y: (H, W*C) float32 rows of interleaved channels; g: (K,) window. Fills ``row_sums[i]`` with the
        sum of the SSIM map over output row i and, if ``want_grad``, the map's derivatives with respect to
        x's blurred mean (p_m), blurred square (p_e) and the blurred product (p_c), each (H-K+1, (W-K+1)*C)."""
        two = np.float32(2.0)
        c1 = np.float32(c1)
        c2 = np.float32(c2)
        taps = g.shape[0]
        out_rows = x.shape[0] - taps + 1
        width = x.shape[1]
        out_width = width - (taps - 1) * channels
        for i in prange(out_rows):
            # One simple loop per moment: each vectorises (a loop updating all five does not).
            v0 = np.zeros(width, np.float32)
            v1 = np.zeros(width, np.float32)
            v2 = np.zeros(width, np.float32)
            v3 = np.zeros(width, np.float32)
            v4 = np.zeros(width, np.float32)
            for t in range(taps):
                w = g[t]
                a = x[i + t]
                b = y[i + t]
                for q in range(width):
                    v0[q] += w * a[q]
                for q in range(width):
                    v1[q] += w * b[q]
                for q in range(width):
                    v2[q] += w * (a[q] * a[q])
                for q in range(width):
                    v3[q] += w * (b[q] * b[q])
                for q in range(width):
                    v4[q] += w * (a[q] * b[q])
            h0 = np.zeros(out_width, np.float32)
            h1 = np.zeros(out_width, np.float32)
            h2 = np.zeros(out_width, np.float32)
            h3 = np.zeros(out_width, np.float32)
            h4 = np.zeros(out_width, np.float32)
            for t in range(taps):
                # Shifted windows as slices: indexing v[q + shift] inside the loop stops it vectorising.
                w = g[t]
                lo = t * channels
                s0 = v0[lo : lo + out_width]
                s1 = v1[lo : lo + out_width]
                s2 = v2[lo : lo + out_width]
                s3 = v3[lo : lo + out_width]
                s4 = v4[lo : lo + out_width]
                for q in range(out_width):
                    h0[q] += w * s0[q]
                for q in range(out_width):
                    h1[q] += w * s1[q]
                for q in range(out_width):
                    h2[q] += w * s2[q]
                for q in range(out_width):
                    h3[q] += w * s3[q]
                for q in range(out_width):
                    h4[q] += w * s4[q]
            # float32 throughout (numba's literals are float64) and no branch or reduction inside: these vectorise.
            value = np.empty(out_width, np.float32)
            if want_grad:
                for q in range(out_width):
                    mx = h0[q]
                    my = h1[q]
                    a1 = two * mx * my + c1
                    a2 = mx * mx + my * my + c1
                    b1 = two * (h4[q] - mx * my) + c2
                    b2 = (h2[q] - mx * mx) + (h3[q] - my * my) + c2
                    lum = a1 / a2
                    cs = b1 / b2
                    value[q] = lum * cs
                    p_m[i, q] = two * (cs * (my * a2 - a1 * mx) / (a2 * a2) + lum * (b1 * mx - my * b2) / (b2 * b2))
                    p_e[i, q] = -lum * b1 / (b2 * b2)
                    p_c[i, q] = two * lum / b2
            else:
                for q in range(out_width):
                    mx = h0[q]
                    my = h1[q]
                    a1 = two * mx * my + c1
                    a2 = mx * mx + my * my + c1
                    b1 = two * (h4[q] - mx * my) + c2
                    b2 = (h2[q] - mx * mx) + (h3[q] - my * my) + c2
                    value[q] = (a1 / a2) * (b1 / b2)
            total = 0.0
            for q in range(out_width):
                total += value[q]
            row_sums[i] = total

    @njit(parallel=True, cache=True)
    def backward(x, y, g, channels, p_m, p_e, p_c, scale, grad_x):
        """grad_x (H, W*C) = scale * (G^T p_m + 2 x G^T p_e + y G^T p_c), G the valid separable blur."""
        two = np.float32(2.0)
        scale = np.float32(scale)
        taps = g.shape[0]
        out_rows = p_m.shape[0]
        out_width = p_m.shape[1]
        rows, width = x.shape
        spread_m = np.zeros((out_rows, width), np.float32)
        spread_e = np.zeros((out_rows, width), np.float32)
        spread_c = np.zeros((out_rows, width), np.float32)
        for o in prange(out_rows):
            src_m = p_m[o]
            src_e = p_e[o]
            src_c = p_c[o]
            for t in range(taps):
                w = g[t]
                lo = t * channels
                dst_m = spread_m[o, lo : lo + out_width]
                dst_e = spread_e[o, lo : lo + out_width]
                dst_c = spread_c[o, lo : lo + out_width]
                for q in range(out_width):
                    dst_m[q] += w * src_m[q]
                for q in range(out_width):
                    dst_e[q] += w * src_e[q]
                for q in range(out_width):
                    dst_c[q] += w * src_c[q]
        for r in prange(rows):
            acc_m = np.zeros(width, np.float32)
            acc_e = np.zeros(width, np.float32)
            acc_c = np.zeros(width, np.float32)
            for t in range(max(0, r - out_rows + 1), min(taps, r + 1)):
                w = g[t]
                row_m = spread_m[r - t]
                row_e = spread_e[r - t]
                row_c = spread_c[r - t]
                for q in range(width):
                    acc_m[q] += w * row_m[q]
                for q in range(width):
                    acc_e[q] += w * row_e[q]
                for q in range(width):
                    acc_c[q] += w * row_c[q]
            xr = x[r]
            yr = y[r]
            out = grad_x[r]
            for q in range(width):
                out[q] = scale * (acc_m[q] + two * xr[q] * acc_e[q] + yr[q] * acc_c[q])

    return forward, backward


_KERNELS = None


def _kernels():
    global _KERNELS
    if _KERNELS is None:
        _KERNELS = _fused_kernels()
    return _KERNELS


def _rows(image: Float[Tensor, "C H W"]) -> np.ndarray:
    """(H, W*C) float32 rows of interleaved channels (a view when the image is a permuted HWC tensor)."""
    return np.ascontiguousarray(image.detach().permute(1, 2, 0).reshape(image.shape[1], -1).numpy())


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, X: Tensor, Y: Tensor, window: np.ndarray, c1: float, c2: float) -> Tensor:
        forward_kernel, _ = _kernels()
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
                forward_kernel(first, second, window, channels, c1, c2, True, row_sums, *maps)
                partials.append(maps)
            if not grads:
                unused = np.empty((1, 1), np.float32)
                forward_kernel(x, y, window, channels, c1, c2, False, row_sums, unused, unused, unused)
            total += float(row_sums.sum())
            saved.append((x, y, partials))
        ctx.saved = saved
        ctx.window, ctx.grads, ctx.shape = window, grads, X.shape
        ctx.count = n * channels * (height - taps + 1) * (width - taps + 1)
        return X.new_tensor(total / ctx.count)

    @staticmethod
    def backward(ctx, grad_output: Tensor):
        _, backward_kernel = _kernels()
        n, channels, height, width = ctx.shape
        scale = float(grad_output) / ctx.count
        out = [None, None]
        for which in ctx.grads:
            grad = torch.empty(n, height, width, channels, dtype=torch.float32)
            for b, (x, y, partials) in enumerate(ctx.saved):
                first, second = (x, y) if which == 0 else (y, x)
                maps = partials[ctx.grads.index(which)]
                backward_kernel(first, second, ctx.window, channels, *maps, scale, grad[b].view(height, -1).numpy())
            out[which] = grad.permute(0, 3, 1, 2)
        ctx.saved = None
        return out[0], out[1], None, None, None


class SSIMLoss(SSIM):
    """``pytorch_msssim.SSIM`` whose forward runs the compiled kernels where they apply (module docstring)."""

    def forward(self, X: Float[Tensor, "N C H W"], Y: Float[Tensor, "N C H W"]) -> Tensor:
        if not self._fused_applies(X, Y):
            return super().forward(X, Y)
        window = self.win[0].flatten().to(torch.float32).numpy()  # the window pytorch_msssim convolves with
        k1, k2 = self.K
        return _FusedSSIM.apply(X, Y, window, (k1 * self.data_range) ** 2, (k2 * self.data_range) ** 2)

    def _fused_applies(self, X: Tensor, Y: Tensor) -> bool:
        return (
            njit is not None
            and X.dim() == 4
            and X.shape == Y.shape
            and X.device.type == "cpu"
            and Y.device.type == "cpu"
            and X.dtype == Y.dtype == torch.float32
            and min(X.shape[2:]) >= self.win_size
            and self.size_average
            and not self.nonnegative_ssim
        )
