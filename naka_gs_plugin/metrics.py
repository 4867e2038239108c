"""Image quality numbers shared by the demo, the correction trainer, its evaluation and the benches."""

from __future__ import annotations

import math
from typing import Dict, Optional, Tuple

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


LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB luminance weights of linear R, G, B."""


def colour_stats(image: Float[Tensor, "H W 3"]) -> Tuple[Float[Tensor, "3"], float]:
    """``(chromaticity, luminance)`` of an sRGB [0, 1] image in linear light: the r, g, b fractions of its
    mean linear RGB (summing to 1) and its mean linear luminance."""
    import kornia  # here, not at module level: the method config imports this package and stays light

    linear = kornia.color.rgb_to_linear_rgb(image.permute(2, 0, 1).clamp(0, 1)).mean(dim=(1, 2))
    return linear / linear.sum().clamp(min=1e-12), float(linear @ linear.new_tensor(LUMA))


def colour_error(pred: Float[Tensor, "H W 3"], reference: Float[Tensor, "H W 3"]) -> Dict[str, float]:
    """How far ``pred``'s overall colour is from ``reference``'s (sRGB [0, 1], same view): ``chroma_l1``,
    the L1 distance of their linear-light chromaticities (:func:`colour_stats`; 0 = same cast), the
    signed ``chroma_{r,g,b}`` differences (pred - reference), and ``luma_ratio``, pred's mean linear
    luminance over the reference's (1 = same exposure)."""
    (c_pred, l_pred), (c_ref, l_ref) = colour_stats(pred), colour_stats(reference)
    diff = c_pred - c_ref
    return {
        "chroma_l1": float(diff.abs().sum()),
        **{f"chroma_{name}": float(d) for name, d in zip("rgb", diff)},
        "luma_ratio": l_pred / max(l_ref, 1e-12),
    }
