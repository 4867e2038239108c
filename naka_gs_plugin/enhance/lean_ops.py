"""Fused bfloat16 GroupNorm (+ residual) + GELU for the correction network's lean inference (CPU).

In the lean forward (:func:`naka_gs_plugin.enhance.correction.lean_predict_maps`) every conv unit
is ``conv -> GroupNorm -> GELU`` (a residual block's second unit: ``-> + input -> GELU``) on
bfloat16 activations of up to 32 x 1172 x 1764. PyTorch runs GroupNorm (two passes), the add and
the erf-GELU (evaluated in float32, slower than the float32 op itself) as separate kernels: about
45% of the lean forward's time went there on this 2-core CPU. Here one pass gathers the group
statistics and one pass applies them, adds the residual and takes GELU from a 65,536-entry table:
a bfloat16 input has only that many values, and the table holds PyTorch's own float32 erf-GELU of
each, rounded to bfloat16 -- exactly what ``F.gelu`` returns on that value. Every intermediate is
rounded to bfloat16 where PyTorch's sequence of ops rounds it; the one difference is the
normalisation, ``x * a_c + b_c`` with ``a_c = gamma_c / sqrt(var_g + eps)`` and
``b_c = beta_c - mean_g * a_c``, which can round the last bit the other way (tested against
:func:`group_norm_gelu_reference`).

Kernels are numba (``cache=True``), parallel over pixels of channels-last tensors, reading and
writing bfloat16 through its 16-bit pattern (numba has no bfloat16 type).
"""

from __future__ import annotations

import functools
from typing import Optional

import numba
import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Float
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic
from torch import Tensor

_CHUNK = 4096
"""Pixels per work item of the statistics pass (partial sums in float64, then combined)."""


@intrinsic
def _bits_to_f32(typingctx, bits):
    """float32 whose bit pattern is the uint32 ``bits``."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.uint32), codegen


@intrinsic
def _f32_to_bits(typingctx, value):
    """uint32 bit pattern of the float32 ``value``."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.uint32(types.float32), codegen


@njit(cache=True, inline="always")
def _bf16_to_f32(h):
    return _bits_to_f32(np.uint32(h) << np.uint32(16))


@njit(cache=True, inline="always")
def _f32_to_bf16(v):
    """Round to nearest even, as PyTorch's float -> bfloat16 conversion (NaN -> quiet NaN)."""
    if v != v:
        return np.uint16(0x7FC0)
    u = _f32_to_bits(v)
    u = u + np.uint32(0x7FFF) + ((u >> np.uint32(16)) & np.uint32(1))
    return np.uint16(u >> np.uint32(16))


@njit(parallel=True, cache=True)
def _group_moments(x, groups):
    """Per-group mean and population variance of a ``[pixels, channels]`` bfloat16 pattern array.

    Sums of ``x - x[0]`` per channel (the shift keeps float32 sums of squares free of cancellation
    when a channel's mean dwarfs its spread), in float32 over a chunk of pixels (contiguous channels:
    vectorised) and float64 across chunks and for the final moments."""
    n_pix, n_ch = x.shape
    per = n_ch // groups
    ref = np.empty(n_ch, np.float32)
    for c in range(n_ch):
        ref[c] = _bf16_to_f32(x[0, c])
    n_chunks = (n_pix + _CHUNK - 1) // _CHUNK
    partial = np.zeros((n_chunks, 2, n_ch))
    for k in prange(n_chunks):
        s = np.zeros(n_ch, np.float32)
        q = np.zeros(n_ch, np.float32)
        for p in range(k * _CHUNK, min(n_pix, (k + 1) * _CHUNK)):
            for c in range(n_ch):
                d = _bf16_to_f32(x[p, c]) - ref[c]
                s[c] += d
                q[c] += d * d
        partial[k, 0] = s
        partial[k, 1] = q
    sums = partial.sum(axis=0)
    mean = np.zeros(groups)
    second = np.zeros(groups)
    for c in range(n_ch):
        m_d = sums[0, c] / n_pix  # E[x - ref], E[(x - ref)^2] of channel c
        r = np.float64(ref[c])
        mean[c // per] += (r + m_d) / per
        second[c // per] += (sums[1, c] / n_pix + 2.0 * r * m_d + r * r) / per
    return mean, np.maximum(second - mean * mean, 0.0)


@njit(parallel=True, cache=True)
def _apply(x, scale, shift, residual, table, act, out):
    """``out = gelu(bf16(bf16(x * scale + shift) + residual))`` per pixel row (residual optional)."""
    n_pix, n_ch = x.shape
    has_res = residual.shape[0] == n_pix
    for p in prange(n_pix):
        for c in range(n_ch):
            h = _f32_to_bf16(_bf16_to_f32(x[p, c]) * scale[c] + shift[c])
            if has_res:
                h = _f32_to_bf16(_bf16_to_f32(h) + _bf16_to_f32(residual[p, c]))
            out[p, c] = table[h] if act else h


_GELU_TABLE: Optional[np.ndarray] = None


def gelu_table() -> np.ndarray:
    """uint16[65536]: the bfloat16 pattern of ``F.gelu`` (erf form) of every bfloat16 pattern."""
    global _GELU_TABLE
    if _GELU_TABLE is None:
        every = torch.arange(1 << 16, dtype=torch.int32).to(torch.int16).view(torch.bfloat16)
        _GELU_TABLE = F.gelu(every.float()).to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16)
    return _GELU_TABLE


def _patterns(x: Tensor) -> np.ndarray:
    """``[pixels, C]`` uint16 view of a channels-last ``[1, C, H, W]`` bfloat16 tensor (no copy)."""
    return x.permute(0, 2, 3, 1).view(torch.int16).numpy().reshape(-1, x.shape[1]).view(np.uint16)


def supported(x: Tensor) -> bool:
    """Whether :func:`group_norm_gelu` takes ``x``: one bfloat16 channels-last CPU image."""
    return (
        x.dtype == torch.bfloat16
        and x.device.type == "cpu"
        and x.ndim == 4
        and x.shape[0] == 1
        and x.is_contiguous(memory_format=torch.channels_last)
    )


def _threads_as_torch(fn):
    """Run numba kernels on PyTorch's intra-op thread count, and keep that count: numba's OpenMP
    pool, started on first use, resets the shared OpenMP runtime's (hence PyTorch's) count."""

    def wrapped(*args, **kwargs):
        threads = torch.get_num_threads()
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        try:
            return fn(*args, **kwargs)
        finally:
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)

    return functools.wraps(fn)(wrapped)


@_threads_as_torch
def group_norm_gelu(
    x: Float[Tensor, "1 C H W"],
    norm: torch.nn.GroupNorm,
    residual: Optional[Float[Tensor, "1 C H W"]] = None,
    act: bool = True,
    inplace: bool = False,
) -> Float[Tensor, "1 C H W"]:
    """``gelu(group_norm(x) + residual)`` (GELU if ``act``, residual if given) in bfloat16, fused.

    ``x`` and ``residual``: bfloat16, channels-last (see :func:`supported`); ``norm``'s affine
    parameters may be float32 or bfloat16. Returns a new channels-last bfloat16 tensor, or ``x``
    overwritten if ``inplace`` (each element is read before it is written, by the same thread)."""
    if not supported(x) or (residual is not None and (not supported(residual) or residual.shape != x.shape)):
        raise ValueError("group_norm_gelu needs bfloat16 channels-last [1, C, H, W] CPU tensors of one shape")
    src = _patterns(x)
    mean, var = _group_moments(src, norm.num_groups)
    per = x.shape[1] // norm.num_groups
    rstd = torch.from_numpy(1.0 / np.sqrt(var + norm.eps)).repeat_interleave(per)
    mean_c = torch.from_numpy(mean).repeat_interleave(per)
    weight, bias = norm.weight.detach().double(), norm.bias.detach().double()
    scale = (weight * rstd).float()
    shift = (bias - mean_c * weight * rstd).float()
    out = x if inplace else torch.empty_like(x, memory_format=torch.channels_last)
    res = _patterns(residual) if residual is not None else np.empty((0, 0), np.uint16)
    _apply(src, scale.numpy(), shift.numpy(), res, gelu_table(), act, _patterns(out))
    return out


def norm_act(
    x: Float[Tensor, "1 C H W"],
    norm: torch.nn.GroupNorm,
    residual: Optional[Float[Tensor, "1 C H W"]] = None,
    act: bool = True,
) -> Float[Tensor, "1 C H W"]:
    """:func:`group_norm_gelu` in place of ``x`` where it applies (:func:`supported`), else the PyTorch
    reference; either way ``x`` (a fresh convolution output) must not be used afterwards."""
    if supported(x) and (residual is None or (supported(residual) and residual.shape == x.shape)):
        return group_norm_gelu(x, norm, residual, act, inplace=True)
    return group_norm_gelu_reference(x, norm, residual, act)


def group_norm_gelu_reference(
    x: Float[Tensor, "1 C H W"],
    norm: torch.nn.GroupNorm,
    residual: Optional[Float[Tensor, "1 C H W"]] = None,
    act: bool = True,
) -> Float[Tensor, "1 C H W"]:
    """The same with PyTorch ops (what the lean forward runs where numba does not apply)."""
    y = F.group_norm(x, norm.num_groups, norm.weight.to(x.dtype), norm.bias.to(x.dtype), norm.eps)
    if residual is not None:
        y = y.add_(residual)
    return torch._C._nn.gelu_(y) if act else y
