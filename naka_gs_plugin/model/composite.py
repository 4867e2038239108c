"""The render onto its background, then a training view's appearance: the last image operations before the loss.

Splatfacto composites the rasterizer's premultiplied colour onto the background and clamps,
``clamp(render + (1 - alpha) * background, 0, 1)``; in training naka-gs then applies the view's appearance
(:mod:`naka_gs_plugin.model.appearance`), ``clamp(rgb * gain + offset, 0, 1)``. :func:`composite_torch` is that
chain as PyTorch operations, the readable reference. On a CPU its seven full-size operations forward and a dozen in
autograd's backward cost as much as a small scene's rasterizer call, so :func:`composite` runs the compiled kernels
of :mod:`.composite_cpu_fast` (one pass each way, same values) for float32 CPU tensors with a constant background,
and the reference for anything else (CUDA, float64, a background that requires a gradient, numba missing).
Colours are display-referred sRGB in [0, 1]; ``alpha`` is the accumulated opacity in [0, 1].
"""

from __future__ import annotations

from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.cpu import numba_fast_path


def clamp01(x: Tensor) -> Tensor:
    """``torch.clamp(x, 0, 1)``, its gradient passed strictly inside (``0 < x < 1``) and neither at a bound nor for
    NaN. torch's own clamp has changed its rule at an exact bound between releases (2.1 passes the gradient there,
    2.14 does not); one explicit rule keeps the reference and the compiled kernels equal on every supported torch."""
    return torch.where((x > 0) & (x < 1), x, x.detach().clamp(0.0, 1.0))


def composite_torch(
    render: Float[Tensor, "*batch H W 3"],
    alpha: Float[Tensor, "*batch H W 1"],
    background: Float[Tensor, " 3"],
    gain: Optional[Float[Tensor, " 3"]] = None,
    offset: Optional[Float[Tensor, " 3"]] = None,
) -> Float[Tensor, "*batch H W 3"]:
    """``clamp(render + (1 - alpha) * background, 0, 1)``, then with ``gain`` and ``offset`` (a view's
    appearance) ``clamp(rgb * gain + offset, 0, 1)``."""
    rgb = clamp01(render + (1 - alpha) * background)
    if gain is not None:
        rgb = clamp01(rgb * gain + offset)
    return rgb


def _fast_path():
    """:func:`.composite_cpu_fast.composite_cpu_fast`, or None where numba does not import."""
    return numba_fast_path("naka_gs_plugin.model.composite_cpu_fast", "composite_cpu_fast")


def composite(
    render: Float[Tensor, "*batch H W 3"],
    alpha: Float[Tensor, "*batch H W 1"],
    background: Float[Tensor, " 3"],
    gain: Optional[Float[Tensor, " 3"]] = None,
    offset: Optional[Float[Tensor, " 3"]] = None,
) -> Float[Tensor, "*batch H W 3"]:
    """:func:`composite_torch`'s values and gradients, compiled where it applies (module docstring)."""
    tensors = [render, alpha, background] + ([gain, offset] if gain is not None else [])
    if (
        all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
        and not background.requires_grad
        and background.shape == (3,)
        and render.shape[-1] == 3
        and alpha.shape == render.shape[:-1] + (1,)
        and (gain is None or gain.shape == offset.shape == (3,))
        and _fast_path() is not None
    ):
        return _fast_path()(render, alpha, background, gain, offset)
    return composite_torch(render, alpha, background, gain, offset)
