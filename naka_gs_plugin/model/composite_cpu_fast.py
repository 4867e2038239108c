"""Compiled CPU compositing and appearance: numba kernels with a hand-written backward (the fast path of
:mod:`.composite`, whose :func:`~naka_gs_plugin.model.composite.composite_torch` is the readable reference).

Forward, one pass over each image row's interleaved RGB values (``prange`` over rows; the background, gain, offset
and ``1 - alpha`` laid out per value, so the pass runs as vectors): ``c = render + (1 - alpha) * background``,
``r = clamp(c, 0, 1)`` and, with an appearance, ``clamp(r * gain + offset, 0, 1)``, in float32 operation for
operation as the reference (no ``fastmath``: no contraction into FMAs), so the values are the reference's. Backward,
one such pass recomputing ``c`` and ``r``: torch's clamp gradient (passed only strictly inside, ``0 < x < 1``; none at
a bound or for NaN) and the render's gradient; then per pixel alpha's, and the gain's and offset's as float64 sums
per image row in pixel order, added up in row order afterwards: the result does not depend on the thread count.
Kernels compile on first use and are cached on disk by numba (as :mod:`.rasterize_cpu_fast`'s).
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


@njit(cache=True)
def _per_slot(values, slots):
    """(3,) -> (slots,): ``values[q % 3]`` for each slot ``q`` of a row of interleaved RGB."""
    out = np.empty(slots, values.dtype)
    for q in range(slots):
        out[q] = values[q % 3]
    return out


@njit(cache=True, inline="always")
def _transmittance(alpha_row, slots):
    """``1 - alpha`` of a row's pixels, once per slot of its interleaved RGB: the per-slot operands let the loops
    over a row's slots run as vectors, where a loop over its pixels with the three channels inside stays scalar."""
    out = np.empty(slots, np.float32)
    one = np.float32(1.0)
    for j in range(alpha_row.shape[0]):
        t = one - alpha_row[j]
        out[3 * j] = t
        out[3 * j + 1] = t
        out[3 * j + 2] = t
    return out


@njit(parallel=True, cache=True)
def _forward_kernel(render, alpha, background, gain, offset, appearance, out):
    """render, out: (R, 3W) rows of interleaved RGB; alpha: (R, W); background, gain, offset: (3,)."""
    slots = out.shape[1]
    back, gains, offsets = _per_slot(background, slots), _per_slot(gain, slots), _per_slot(offset, slots)
    for i in prange(out.shape[0]):
        transmit = _transmittance(alpha[i], slots)
        row, dst = render[i], out[i]
        if appearance:
            for q in range(slots):
                dst[q] = _clamp01(_clamp01(row[q] + transmit[q] * back[q]) * gains[q] + offsets[q])
        else:
            for q in range(slots):
                dst[q] = _clamp01(row[q] + transmit[q] * back[q])


@njit(parallel=True, cache=True)
def _backward_kernel(
    render, alpha, background, gain, offset, appearance, grad_out, grad_render, grad_alpha, row_gain, row_offset
):
    """render, grad_out, grad_render: (R, 3W); alpha, grad_alpha: (R, W); row_gain, row_offset: (R, 3) float64
    per-row sums of the gain's and the offset's gradients, in pixel order."""
    slots = grad_out.shape[1]
    back, gains, offsets = _per_slot(background, slots), _per_slot(gain, slots), _per_slot(offset, slots)
    zero = np.float32(0.0)
    for i in prange(grad_out.shape[0]):
        transmit = _transmittance(alpha[i], slots)
        row, g_out, g_render = render[i], grad_out[i], grad_render[i]
        if appearance:
            clamped = np.empty(slots, np.float32)  # clamp(c, 0, 1): what the gain multiplies
            g_inner = np.empty(slots, np.float32)  # the gradient through the appearance's clamp
            for q in range(slots):
                c = row[q] + transmit[q] * back[q]
                r = _clamp01(c)
                g = g_out[q] if _inside01(r * gains[q] + offsets[q]) else zero
                clamped[q] = r
                g_inner[q] = g
                g_render[q] = g * gains[q] if _inside01(c) else zero
            sum_gain = np.zeros(3, np.float64)
            sum_offset = np.zeros(3, np.float64)
            for j in range(alpha.shape[1]):
                for k in range(3):
                    g = g_inner[3 * j + k]
                    sum_gain[k] += g * clamped[3 * j + k]
                    sum_offset[k] += g
            for k in range(3):
                row_gain[i, k] = sum_gain[k]
                row_offset[i, k] = sum_offset[k]
        else:
            for q in range(slots):
                c = row[q] + transmit[q] * back[q]
                g_render[q] = g_out[q] if _inside01(c) else zero
        for j in range(alpha.shape[1]):
            g_alpha = zero
            for k in range(3):
                g_alpha -= g_render[3 * j + k] * background[k]
            grad_alpha[i, j] = g_alpha


def _rows(t: Tensor) -> np.ndarray:
    """(..., H, W, C) -> (rows, W * C) NumPy view of contiguous rows (a copy where ``t``'s are not)."""
    return t.detach().contiguous().reshape(-1, t.shape[-2] * t.shape[-1]).numpy()


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
