"""The degradation pipeline: listed effects only, in a fixed physical order, in linear light.

Images are torch tensors ``[H, W, 3]`` float64. ``clean`` is **linear** radiance in [0, 1]
(normal light). The stages, each applied only when the spec lists it:

1. ``exposure``        x *= factor
2. ``exposure_jitter`` x *= per-view multiplier ``2 ** N(0, stops)``
3. ``light_sources``   x += lamp cores (linear, may exceed 1); x += bloom = blur(max(x - 1, 0)) * strength
4. ``color_cast``      x *= gains (R, G, B)
5. ``noise``           x = shot_gain * Poisson(x / shot_gain) + N(0, read_std**2)
   -- sensor: x = clip(x, 0, 1) (always; a file cannot hold values outside [0, 1]) --
6. ``response``        sRGB transfer curve or ``x ** (1 / gamma)``; **not listed: values stay linear**
7. ``quantize``        x = round(255 x) / 255 and 8-bit files; **not listed: 16-bit PNG** (1/65535 steps)
8. ``jpeg``            JPEG file at ``quality`` (training images only; PNG otherwise)

Ground truth (``test/``, ``train_gt/``) is the clean linear image through the sensor clip,
``response`` and ``quantize`` only: encoded exactly like the training images, without any
degradation, so a spec with no effects writes training images identical to their truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import cv2
import kornia
import numpy as np
import torch
from jaxtyping import Float
from PIL import Image
from torch import Tensor

from naka_gs_plugin.sim.spec import (
    ColorCast,
    Effect,
    Exposure,
    ExposureJitter,
    Jpeg,
    LightSources,
    Noise,
    Quantize,
    Response,
)


def srgb_to_linear(x: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
    """sRGB-encoded [0, 1] -> linear [0, 1] (kornia's piecewise sRGB curve)."""
    return kornia.color.rgb_to_linear_rgb(x.permute(2, 0, 1)).permute(1, 2, 0)


def linear_to_srgb(x: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
    """Linear [0, 1] -> sRGB-encoded [0, 1]."""
    return kornia.color.linear_rgb_to_rgb(x.permute(2, 0, 1)).permute(1, 2, 0)


def bloom(x: Float[Tensor, "H W 3"], sigma_px: float, strength: float) -> Float[Tensor, "H W 3"]:
    """Glare: the above-white part ``max(x - 1, 0)`` blurred (Gaussian, ``sigma_px``) times ``strength``."""
    excess = (x - 1.0).clamp(min=0.0).permute(2, 0, 1)[None]
    k = 2 * int(np.ceil(3 * sigma_px)) + 1
    blurred = kornia.filters.gaussian_blur2d(excess, (k, k), (sigma_px, sigma_px), border_type="constant")
    return x + strength * blurred[0].permute(1, 2, 0)


def add_noise(x: Float[Tensor, "H W 3"], noise: Noise, generator: torch.Generator) -> Float[Tensor, "H W 3"]:
    """Poisson-Gaussian sensor noise: mean ``x``, variance ``shot_gain * x + read_std**2``."""
    shot = x
    if noise.shot_gain > 0:
        shot = torch.poisson(x.clamp(min=0.0) / noise.shot_gain, generator=generator) * noise.shot_gain
    read = torch.randn(x.shape, generator=generator, dtype=x.dtype) * noise.read_std
    return shot + read


def sensor(
    clean: Float[Tensor, "H W 3"],
    effects: Sequence[Effect],
    exposure_multiplier: float = 1.0,
    lamps: Optional[Float[Tensor, "H W 3"]] = None,
    generator: Optional[torch.Generator] = None,
) -> Float[Tensor, "H W 3"]:
    """Stages 1-5 and the sensor clip: linear [0, 1] values as recorded by the sensor.

    ``exposure_multiplier`` is the view's jitter (used only if ``exposure_jitter`` is listed, the
    caller draws it); ``lamps`` the view's linear lamp image (required iff ``light_sources`` is
    listed); ``generator`` seeds the noise (required iff ``noise`` is listed).
    """
    x = clean.to(torch.float64)
    for effect in effects:
        if isinstance(effect, Exposure):
            x = x * effect.factor
        elif isinstance(effect, ExposureJitter):
            x = x * exposure_multiplier
        elif isinstance(effect, LightSources):
            x = bloom(x + lamps, effect.bloom_sigma_px, effect.bloom_strength)
        elif isinstance(effect, ColorCast):
            x = x * torch.tensor(effect.gains, dtype=x.dtype)
        elif isinstance(effect, Noise):
            x = add_noise(x, effect, generator)
    return x.clamp(0.0, 1.0)


def encode(linear: Float[Tensor, "H W 3"], effects: Sequence[Effect]) -> Float[Tensor, "H W 3"]:
    """Stages 6-7: the listed response (else identity: linear output) and 8-bit rounding if listed."""
    x = linear
    for effect in effects:
        if isinstance(effect, Response):
            x = linear_to_srgb(x) if effect.curve == "srgb" else x.pow(1.0 / effect.gamma)
        elif isinstance(effect, Quantize):
            x = torch.round(x * 255.0) / 255.0
    return x.clamp(0.0, 1.0)


def image_suffix(effects: Sequence[Effect], ground_truth: bool) -> str:
    """``.jpg`` for training images when ``jpeg`` is listed, else ``.png``."""
    return ".jpg" if not ground_truth and any(isinstance(e, Jpeg) for e in effects) else ".png"


def write_image(path: Path, encoded: Float[Tensor, "H W 3"], effects: Sequence[Effect], ground_truth: bool) -> None:
    """Stage 8 and storage: JPEG (if listed, training images), 8-bit PNG with ``quantize``, else 16-bit PNG.

    ``encoded`` is in [0, 1] (already through :func:`encode`). Files are written deterministically.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = encoded.detach().cpu().numpy()
    jpeg = next((e for e in effects if isinstance(e, Jpeg)), None)
    if not any(isinstance(e, Quantize) for e in effects):
        cv2.imwrite(str(path), np.round(arr[..., ::-1] * 65535.0).astype(np.uint16))
        return
    img = Image.fromarray(np.round(arr * 255.0).astype(np.uint8))
    if jpeg is not None and not ground_truth:
        img.save(path, format="JPEG", quality=jpeg.quality)
    else:
        img.save(path, format="PNG")
