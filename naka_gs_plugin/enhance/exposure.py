"""Scene exposure: one tone curve that lifts a too-dark enhanced scene to a normal photo's exposure.

The correction network leaves the exposure about where the Naka stretch puts it, and the stretch takes
its maximum from the brightest pixels: in captures with lamps or highlights (RealX3D) the enhanced views
are far darker than normal-light photos. Like a camera's average metering, the scene's *metered level*,
the mean luminance in linear light (sRGB-encoded to compare with pixel values), is brought to that of
normal-light photos by one power curve ``y = x ** g`` with ``g <= 1`` shared by every view: it keeps black
at 0, white at 1, the order of values and the cross-view consistency (a per-view curve would give each
view its own appearance). Scenes already at or above the target are left alone: a bright night scene is
not darkened.

Metering in linear light is what tells a dark-toned scene from an under-exposed one: a few bright areas
(sky through foliage) carry a large share of the light, so a scene of dark leaves under a bright sky
meters as exposed although its mean sRGB value is low. On LOM's normal-light photos the mean sRGB value
ranges 0.36-0.54 between scenes and the metered level only 0.50-0.58 (docs/real-scenes.md).

Images are sRGB-encoded in [0, 1], channel-last ``[H, W, 3]``.
"""

from __future__ import annotations

from typing import List, Literal, Sequence

import torch
from jaxtyping import Float
from torch import Tensor

METERED_TARGET = 0.505
"""Metered level (sRGB encoding of the mean linear luminance) of LOL's 500 normal-light photos (mean;
s.d. 0.10, median 0.505): the exposure a normal photo of an indoor scene has."""

MIDDLE_GREY = 0.4613
"""sRGB encoding of 18 % linear reflectance: the target of ``mean`` metering (runs saved before the
metering option existed)."""

MIN_GAMMA = 0.2
"""Strongest lift allowed: a nearly black scene (noise only) is not stretched into a grey wash."""

Metering = Literal["luminance", "mean"]
"""``luminance``: sRGB encoding of the mean Rec. 709 luminance in linear light (a camera's average
metering); ``mean``: the mean sRGB value over every pixel and channel."""

LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB luminance weights of linear R, G, B."""


def scene_mean(images: Sequence[Float[Tensor, "H W 3"]]) -> float:
    """Mean over every pixel and channel of ``images`` (views may differ in size; each pixel weighs the same)."""
    total = sum(float(im.sum(dtype=torch.float64)) for im in images)
    return total / max(sum(im.numel() for im in images), 1)


def _linear(srgb: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
    """sRGB [0, 1] -> linear RGB, channel-last (kornia's transfer function, which wants channels first)."""
    # Imported here: every ns-* command imports the method config, hence this module, and stays light.
    import kornia

    as_image = srgb.reshape(-1, 3).T[:, :, None]  # [3, N, 1]
    return kornia.color.rgb_to_linear_rgb(as_image)[:, :, 0].T.reshape(srgb.shape)


def _luminance(srgb: Float[Tensor, "N 3"]) -> float:
    """Mean linear luminance of sRGB pixels."""
    return float((_linear(srgb) @ srgb.new_tensor(LUMA)).mean())


def _encode(linear: float) -> float:
    """Linear [0, 1] -> sRGB [0, 1] of one grey level."""
    import kornia

    return float(kornia.color.linear_rgb_to_rgb(torch.full((3, 1, 1), linear, dtype=torch.float64))[0, 0, 0])


def metered_level(images: Sequence[Float[Tensor, "H W 3"]], metering: Metering = "luminance") -> float:
    """The scene's exposure as ``metering`` reads it, in sRGB [0, 1] (see :data:`Metering`)."""
    if metering == "mean":
        return scene_mean(images)
    return _encode(_luminance(torch.cat([im.reshape(-1, 3) for im in images]).double().clamp(0.0, 1.0)))


def lift_gamma(
    images: Sequence[Float[Tensor, "H W 3"]],
    target: float = METERED_TARGET,
    metering: Metering = "luminance",
    stride: int = 7,
) -> float:
    """The exponent ``g`` in ``[MIN_GAMMA, 1]`` for which ``images ** g`` meter at ``target`` (1 when the
    scene already meters at least ``target``). Bisection on a strided sample of the pixels: the level of
    ``x ** g`` falls monotonically as ``g`` grows."""
    if not 0.0 < target < 1.0:
        raise ValueError(f"exposure target must be in (0, 1), got {target!r}")
    if metering == "mean":
        sample = torch.cat([im.reshape(-1)[::stride] for im in images]).double().clamp(0.0, 1.0)
        level, goal = (lambda g: float(sample.pow(g).mean())), target
    elif metering == "luminance":
        sample = torch.cat([im.reshape(-1, 3)[::stride] for im in images]).double().clamp(0.0, 1.0)
        # Compared in linear light: one decode of the target instead of an encode per step.
        level, goal = (lambda g: _luminance(sample.pow(g))), float(_linear(torch.full((1, 3), target))[0, 0])
    else:
        raise ValueError(f"exposure metering must be luminance or mean, got {metering!r}")
    if sample.numel() == 0 or level(1.0) >= goal:
        return 1.0
    lo, hi = MIN_GAMMA, 1.0
    if level(lo) <= goal:
        return lo
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if level(mid) > goal:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def apply_gamma(images: Sequence[Float[Tensor, "H W 3"]], gamma: float) -> List[Float[Tensor, "H W 3"]]:
    """``images ** gamma`` (clipped to [0, 1] first); the inputs themselves when ``gamma == 1``."""
    if gamma == 1.0:
        return list(images)
    return [im.clamp(0.0, 1.0).pow(gamma) for im in images]
