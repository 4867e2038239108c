"""Naka-Rushton pre-enhancement (paper Sec. 3.1; reference: ``naka_color_correction.py``).

Per pixel and per channel the response is ``R = I^n / (I^n + sigma^n)`` (sigma 0.05, n 1 in the
reference), followed by a linear min-max stretch to [0, 1] whose minimum and maximum are taken over one
image (all pixels and channels jointly), as in the reference (pooling them over the scene's views was no
better on the LOM protocol: records/2026-11-27-levers.md).

Images are sRGB-encoded values in [0, 1], channel-last ``[..., H, W, 3]`` (nerfstudio's layout).
Everything here is batched, differentiable and finite everywhere, including black, constant and
saturated frames where the stretch has zero range (the reference then returns all zeros).
"""

from __future__ import annotations

from typing import Tuple

import torch
from jaxtyping import Float
from torch import Tensor

RANGE_EPS = 1e-6
"""Below this stretch range the output is all zeros, as in the reference (``_to_01_linear``)."""

_POW_EPS = 1e-12
"""Floor for ``I`` inside ``I**n``: keeps the gradient of ``x**n`` finite at 0 when ``n < 1``."""


def naka_rushton(
    images: Float[Tensor, "*batch H W C"], sigma: float = 0.05, n: float = 1.0
) -> Float[Tensor, "*batch H W C"]:
    """Naka-Rushton response ``I^n / (I^n + sigma^n)`` per pixel and channel; negatives clip to 0."""
    if sigma <= 0 or n <= 0:
        raise ValueError(f"Naka-Rushton needs sigma > 0 and n > 0, got sigma={sigma}, n={n}")
    if images.is_floating_point() and not torch.isfinite(images).all():
        bad = int((~torch.isfinite(images)).any(dim=-1).sum())
        raise ValueError(f"Naka-Rushton input has {bad} NaN/Inf pixels -- fix the image (re-export it as 8/16-bit PNG)")
    x = images.clamp(min=0.0)
    if n == 1.0:
        return x / (x + sigma)
    xn = x.clamp(min=_POW_EPS) ** n
    return xn / (xn + sigma**n)


def stretch_stats(response: Float[Tensor, "*batch H W C"]) -> Tuple[Float[Tensor, "*batch"], Float[Tensor, "*batch"]]:
    """Minimum and maximum of each image over all its pixels and channels."""
    flat = response.flatten(start_dim=-3)
    return flat.amin(dim=-1), flat.amax(dim=-1)


def linear_stretch(
    response: Float[Tensor, "*batch H W C"], lo: Float[Tensor, "*batch"], hi: Float[Tensor, "*batch"]
) -> Float[Tensor, "*batch H W C"]:
    """Map ``[lo, hi]`` linearly to ``[0, 1]`` (clipped); all zeros where ``hi - lo < RANGE_EPS``."""
    lo = lo[..., None, None, None]
    span = hi[..., None, None, None] - lo
    stretched = ((response - lo) / span.clamp(min=RANGE_EPS)).clamp(0.0, 1.0)
    return torch.where(span >= RANGE_EPS, stretched, torch.zeros_like(stretched))


def naka_enhance(
    images: Float[Tensor, "*batch H W C"], sigma: float = 0.05, n: float = 1.0
) -> Float[Tensor, "*batch H W C"]:
    """Naka-Rushton response then min-max stretch, with each image's own statistics."""
    response = naka_rushton(images, sigma, n)
    return linear_stretch(response, *stretch_stats(response))
