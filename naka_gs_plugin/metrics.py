"""Image quality numbers shared by the demo, the correction trainer, its evaluation and the benches."""

from __future__ import annotations

import math
from typing import Optional

from jaxtyping import Float
from torch import Tensor

MSE_FLOOR = 1e-10
"""Smallest MSE used (100 dB): identical images give a finite PSNR."""


def psnr(
    pred: Float[Tensor, "*shape"],
    gt: Float[Tensor, "*shape"],
    weight: Optional[Float[Tensor, "*wshape"]] = None,
    eps: float = 0.0,
) -> float:
    """PSNR in dB of two images in [0, 1]: ``10 log10(1 / (MSE + eps))``, MSE over pixels and channels.

    ``weight`` (broadcast against the images, e.g. ``[1, 1, H, W]`` for ``[1, 3, H, W]``) weighs each
    pixel's squared error; ``eps = 1e-8`` is the correction network authors' validation formula.
    """
    err = (pred - gt) ** 2
    if weight is None:
        mse = float(err.mean())
    else:
        channels = err.numel() // weight.numel()
        mse = float((err * weight).sum() / (weight.sum().clamp(min=1e-12) * channels))
    return 10.0 * math.log10(1.0 / max(mse + eps, MSE_FLOOR))
