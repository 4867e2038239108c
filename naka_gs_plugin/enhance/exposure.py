"""Scene exposure: one tone curve that lifts a too-dark enhanced scene to middle grey.

The correction network leaves the exposure about where the Naka stretch puts it, and the stretch takes
its maximum from the brightest pixels: in captures with lamps or highlights (RealX3D) the enhanced views
average 0.23-0.34 where normal-light photos average 0.45-0.49. Like a camera's average metering, the
scene's mean is brought to middle grey (18 % reflectance, 0.461 in sRGB) by one power curve
``y = x ** g`` with ``g <= 1`` shared by every view: it keeps black at 0, white at 1, the order of values
and the cross-view consistency (a per-view curve would give each view its own appearance). Scenes already
at or above the target are left alone: a bright night scene is not darkened.

Images are sRGB-encoded in [0, 1], channel-last ``[H, W, 3]``.
"""

from __future__ import annotations

from typing import List, Sequence

import torch
from jaxtyping import Float
from torch import Tensor

MIDDLE_GREY = 0.4613
"""sRGB encoding of 18 % linear reflectance: the level average metering exposes for."""

MIN_GAMMA = 0.2
"""Strongest lift allowed: a nearly black scene (noise only) is not stretched into a grey wash."""


def scene_mean(images: Sequence[Float[Tensor, "H W 3"]]) -> float:
    """Mean over every pixel and channel of ``images`` (views may differ in size; each pixel weighs the same)."""
    total = sum(float(im.sum(dtype=torch.float64)) for im in images)
    return total / max(sum(im.numel() for im in images), 1)


def lift_gamma(images: Sequence[Float[Tensor, "H W 3"]], target: float = MIDDLE_GREY, stride: int = 7) -> float:
    """The exponent ``g`` in ``[MIN_GAMMA, 1]`` for which the mean of ``images ** g`` is ``target``
    (1 when the scene's mean is already at least ``target``). Bisection on a strided sample of the pixels:
    the mean of ``x ** g`` falls monotonically as ``g`` grows."""
    if not 0.0 < target < 1.0:
        raise ValueError(f"exposure target must be in (0, 1), got {target!r}")
    sample = torch.cat([im.reshape(-1)[::stride] for im in images]).double().clamp(0.0, 1.0)
    if sample.numel() == 0 or float(sample.mean()) >= target:
        return 1.0
    lo, hi = MIN_GAMMA, 1.0
    if float(sample.pow(lo).mean()) <= target:
        return lo
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if float(sample.pow(mid).mean()) > target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def apply_gamma(images: Sequence[Float[Tensor, "H W 3"]], gamma: float) -> List[Float[Tensor, "H W 3"]]:
    """``images ** gamma`` (clipped to [0, 1] first); the inputs themselves when ``gamma == 1``."""
    if gamma == 1.0:
        return list(images)
    return [im.clamp(0.0, 1.0).pow(gamma) for im in images]
