"""Compiled CPU compositing and appearance: numba kernels with a hand-written backward (the fast path of
:mod:`.composite`, whose :func:`~naka_gs_plugin.model.composite.composite_torch` is the readable reference).

Forward, one pass over the pixels (``prange`` over image rows): ``c = render + (1 - alpha) * background``,
``r = clamp(c, 0, 1)`` and, with an appearance, ``clamp(r * gain + offset, 0, 1)``, in float32 operation for
operation as the reference (no ``fastmath``: no contraction into FMAs), so the values are the reference's. Backward,
one pass recomputing ``c`` and ``r``: torch's clamp gradient (passed only strictly inside, ``0 < x < 1``; none at a bound
or for NaN), the render's and alpha's gradients per pixel, and the gain's and offset's as float64 sums per image row
added up in row order afterwards: the result does not depend on the thread count. Kernels compile on first use and
are cached on disk by numba (as :mod:`.rasterize_cpu_fast`'s).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from jaxtyping import Float
from numba import njit, prange
from torch import Tensor

from naka_gs_plugin.cpu import torch_threads_kept, untraced


@njit(cache=True, inline="always")
def _clamp01(v):
    """torch.clamp(v, 0, 1) for a float32 scalar: NaN stays NaN."""
    if v < np.float32(0.0):
        return np.float32(0.0)
    if v > np.float32(1.0):
        return np.float32(1.0)
    return v


@njit(cache=True, inline="always")
def _inside01(v):
    """Where torch's clamp passes the gradient: strictly inside, 0 < v < 1 (at a bound it passes none; NaN none)."""
    return np.float32(0.0) < v < np.float32(1.0)


@njit(parallel=True, cache=True)
def _forward_kernel(render, alpha, background, gain, offset, appearance, out):
    """render, out: (R, W, 3); alpha: (R, W, 1); background, gain, offset: (3,)."""
    one = np.float32(1.0)
    for i in prange(out.shape[0]):
        for j in range(out.shape[1]):
            transmit = one - alpha[i, j, 0]
            for k in range(3):
                v = _clamp01(render[i, j, k] + transmit * background[k])
                if appearance:
                    v = _clamp01(v * gain[k] + offset[k])
                out[i, j, k] = v


@njit(parallel=True, cache=True)
def _backward_kernel(
    render, alpha, background, gain, offset, appearance, grad_out, grad_render, grad_alpha, row_gain, row_offset
):
    """grad_out, grad_render: (R, W, 3); grad_alpha: (R, W, 1); row_gain, row_offset: (R, 3) float64 per-row sums
    of the gain's and the offset's gradients."""
    one = np.float32(1.0)
    for i in prange(grad_out.shape[0]):
        sum_gain = np.zeros(3, np.float64)
        sum_offset = np.zeros(3, np.float64)
        for j in range(grad_out.shape[1]):
            transmit = one - alpha[i, j, 0]
            g_alpha = np.float32(0.0)
            for k in range(3):
                c = render[i, j, k] + transmit * background[k]
                g = grad_out[i, j, k]
                if appearance:
                    r = _clamp01(c)
                    if not _inside01(r * gain[k] + offset[k]):
                        g = np.float32(0.0)
                    sum_gain[k] += g * r
                    sum_offset[k] += g
                    g = g * gain[k]
                if not _inside01(c):
                    g = np.float32(0.0)
                grad_render[i, j, k] = g
                g_alpha -= g * background[k]
            grad_alpha[i, j, 0] = g_alpha
        for k in range(3):
            row_gain[i, k] = sum_gain[k]
            row_offset[i, k] = sum_offset[k]


def _rows(t: Tensor) -> np.ndarray:
    """(..., H, W, C) -> (rows, W, C) NumPy view (a copy only if the leading dimensions cannot be merged)."""
    return t.detach().reshape(-1, t.shape[-2], t.shape[-1]).numpy()


class _Composite(torch.autograd.Function):
    @staticmethod
    @untraced()
    def forward(ctx, render: Tensor, alpha: Tensor, background: Tensor, gain: Tensor, offset: Tensor, appearance: bool):
        out = torch.empty(render.shape, dtype=torch.float32)
        _forward_kernel(
            _rows(render), _rows(alpha), background.detach().numpy(), gain.detach().numpy(),
            offset.detach().numpy(), appearance, _rows(out),
        )  # fmt: skip
        ctx.save_for_backward(render, alpha, background, gain, offset)
        ctx.appearance = appearance
        return out

    @staticmethod
    @untraced()
    def backward(ctx, grad_out: Tensor):
        render, alpha, background, gain, offset = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        grad_render = torch.empty(render.shape, dtype=torch.float32)
        grad_alpha = torch.empty(alpha.shape, dtype=torch.float32)
        rows = _rows(grad_out).shape[0]
        row_gain, row_offset = np.empty((rows, 3)), np.empty((rows, 3))
        _backward_kernel(
            _rows(render), _rows(alpha), background.numpy(), gain.numpy(), offset.numpy(), ctx.appearance,
            _rows(grad_out), _rows(grad_render), _rows(grad_alpha), row_gain, row_offset,
        )  # fmt: skip
        grad_gain = torch.from_numpy(row_gain.sum(0)).float() if ctx.appearance else None
        grad_offset = torch.from_numpy(row_offset.sum(0)).float() if ctx.appearance else None
        return grad_render, grad_alpha, None, grad_gain, grad_offset, None


def composite_cpu_fast(
    render: Float[Tensor, "*batch H W 3"],
    alpha: Float[Tensor, "*batch H W 1"],
    background: Float[Tensor, " 3"],
    gain: Optional[Float[Tensor, " 3"]] = None,
    offset: Optional[Float[Tensor, " 3"]] = None,
) -> Float[Tensor, "*batch H W 3"]:
    """:func:`~naka_gs_plugin.model.composite.composite_torch` for float32 CPU tensors and a background that needs
    no gradient; differentiable in the render, alpha, gain and offset."""
    appearance = gain is not None
    if not appearance:
        gain = offset = torch.ones(3)
    with torch_threads_kept():
        return _Composite.apply(render, alpha, background, gain, offset, appearance)
