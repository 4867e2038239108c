"""Naka-guided chroma-correction network (paper Sec. 3.1; reference: ``ChromaGuidedUNet``).

A U-Net looks at the low-light image and its Naka-Rushton enhancement and predicts two bounded,
smooth maps that act on the *low-frequency* part of the Naka image only::

    I_lf = G_5x5,sigma=1 * I_naka        (zero padding, as the reference)
    I_hf = I_naka - I_lf
    out  = clamp(I_lf * M_mul + M_add + I_hf, 0, 1)
    M_mul = 1 + mul_range * tanh(h_mul)   in (1 - mul_range, 1 + mul_range), 1 channel
    M_add = add_range * tanh(h_add)       in (-add_range, add_range), 3 channels

All images are sRGB-encoded float in [0, 1], channel-first ``[B, 3, H, W]`` (torch layout; the
datamanager's ``[H, W, 3]`` images must be permuted). Any ``H, W >= 1`` works: there is no padding
to a multiple of 8, stride-2 convolutions give ``ceil(H/2)`` and decoders resize to the skip size.

Module names are part of the checkpoint format (the shipped weights and the authors'-checkpoint key
mapping depend on them): ``stem, enc1..3, bottleneck, dec3..1, fuse, mul_head, add_head``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Dict, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

STD_FLOOR = 1e-4
"""Lower clamp of the per-channel standard deviation in the input standardisation (reference)."""


@dataclass
class ChromaGuidedConfig:
    """Architecture hyper-parameters; stored (as a dict) in every checkpoint next to the weights."""

    widths: Tuple[int, int, int, int] = (32, 64, 128, 256)
    """Channels of stem/enc1, enc2, enc3 and the bottleneck."""
    enc_residual: Tuple[int, int, int] = (2, 2, 3)
    """Residual blocks in enc1, enc2, enc3."""
    mul_range: float = 0.6
    """Multiplicative map lies in (1 - mul_range, 1 + mul_range)."""
    add_range: float = 0.25
    """Additive map lies in (-add_range, add_range), image units."""
    lf_sigma: float = 1.0
    """Gaussian sigma (pixels) of the low/high frequency split."""
    lf_kernel: int = 5
    """Gaussian kernel size (pixels, odd) of the frequency split."""

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "ChromaGuidedConfig":
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown ChromaGuidedConfig keys {sorted(unknown)}; expected a subset of {sorted(known)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def _groups(width: int) -> int:
    """Largest divisor of ``width`` that is <= 8 (GroupNorm groups, as the reference)."""
    return max(g for g in range(1, 9) if width % g == 0)


class ConvUnit(nn.Module):
    """3x3 conv (pad 1, no bias) -> GroupNorm -> exact GELU (optional)."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, act: bool = True) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False)
        self.norm = nn.GroupNorm(_groups(c_out), c_out)
        self.act = nn.GELU() if act else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.norm(self.conv(x)))


class ResBlock(nn.Module):
    """conv unit -> conv unit without GELU -> + input -> GELU."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.unit1 = ConvUnit(c, c)
        self.unit2 = ConvUnit(c, c, act=False)
        self.act = nn.GELU()

    def forward(self, x: Tensor) -> Tensor:
        return self.act(x + self.unit2(self.unit1(x)))


class SqueezeExcite(nn.Module):
    """Channel attention: avg-pool -> 1x1 (C -> max(8, C/8)) -> GELU -> 1x1 -> sigmoid -> scale."""

    def __init__(self, c: int) -> None:
        super().__init__()
        hidden = max(8, c // 8)
        self.fc1 = nn.Conv2d(c, hidden, 1)
        self.fc2 = nn.Conv2d(hidden, c, 1)
        self.act = nn.GELU()

    def forward(self, x: Tensor) -> Tensor:
        w = torch.sigmoid(self.fc2(self.act(self.fc1(x.mean(dim=(2, 3), keepdim=True)))))
        return x * w


class Stage(nn.Module):
    """Conv unit ``c_in -> c_out``, ``n_res`` residual blocks, SE (the encoder skip / bottleneck)."""

    def __init__(self, c_in: int, c_out: int, n_res: int) -> None:
        super().__init__()
        self.conv_in = ConvUnit(c_in, c_out)
        self.res = nn.Sequential(*[ResBlock(c_out) for _ in range(n_res)])
        self.se = SqueezeExcite(c_out)

    def forward(self, x: Tensor) -> Tensor:
        return self.se(self.res(self.conv_in(x)))


class EncoderBlock(nn.Module):
    """:class:`Stage` (output kept as skip) then a stride-2 conv unit; returns ``(down, skip)``."""

    def __init__(self, c_in: int, c_out: int, n_res: int) -> None:
        super().__init__()
        self.stage = Stage(c_in, c_out, n_res)
        self.down = ConvUnit(c_out, c_out, stride=2)

    def forward(self, x: Tensor) -> Tuple[Tensor, Tensor]:
        skip = self.stage(x)
        return self.down(skip), skip


class DecoderBlock(nn.Module):
    """Bilinear upsample to the skip's size, concat ``[up, skip]``, :class:`Stage` with 2 residuals."""

    def __init__(self, c_up: int, c_skip: int, c_out: int) -> None:
        super().__init__()
        self.stage = Stage(c_up + c_skip, c_out, 2)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        up = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.stage(torch.cat([up, skip], dim=1))


def standardize(x: Float[Tensor, "B C H W"]) -> Float[Tensor, "B C H W"]:
    """Per sample and channel: subtract the spatial mean, divide by the population std (>= 1e-4)."""
    mean = x.mean(dim=(2, 3), keepdim=True)
    # Same value as clamp(std, 1e-4), but clamping the variance first keeps the gradient finite on
    # constant images (d sqrt(v)/dv is infinite at v = 0, which turned black inputs' gradients NaN).
    std = x.var(dim=(2, 3), keepdim=True, unbiased=False).clamp(min=STD_FLOOR**2).sqrt()
    return (x - mean) / std


def frequency_split(
    naka: Float[Tensor, "B 3 H W"], kernel: int = 5, sigma: float = 1.0
) -> Tuple[Float[Tensor, "B 3 H W"], Float[Tensor, "B 3 H W"]]:
    """``(I_lf, I_hf)``: normalised Gaussian blur with zero padding (as the reference) and the rest."""
    # kornia is imported here, not at module level: every ns-* command imports the method config
    # (hence this module) at start-up and must stay light.
    import kornia

    lf = kornia.filters.gaussian_blur2d(naka, (kernel, kernel), (sigma, sigma), border_type="constant")
    return lf, naka - lf


def apply_maps(
    naka: Float[Tensor, "B 3 H W"],
    mul: Float[Tensor, "B 1 H W"],
    add: Float[Tensor, "B 3 H W"],
    kernel: int = 5,
    sigma: float = 1.0,
) -> Float[Tensor, "B 3 H W"]:
    """``clamp(I_lf * mul + add + I_hf, 0, 1)``; maps must already be at the Naka image's size."""
    if mul.shape[-2:] != naka.shape[-2:] or add.shape[-2:] != naka.shape[-2:]:
        raise ValueError(
            f"maps {tuple(mul.shape)}/{tuple(add.shape)} must match the image size {tuple(naka.shape[-2:])}; "
            "upsample them first"
        )
    lf, hf = frequency_split(naka, kernel, sigma)
    return (lf * mul + add + hf).clamp(0.0, 1.0)


class ChromaGuided(nn.Module):
    """The correction U-Net (5,443,620 parameters with the default config)."""

    def __init__(self, config: ChromaGuidedConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or ChromaGuidedConfig()
        w: Sequence[int] = config.widths
        r: Sequence[int] = config.enc_residual
        if len(w) != 4 or len(r) != 3:
            raise ValueError(f"widths needs 4 entries and enc_residual 3, got {w} and {r}")
        self.stem = ConvUnit(18, w[0])
        self.enc1 = EncoderBlock(w[0], w[0], r[0])
        self.enc2 = EncoderBlock(w[0], w[1], r[1])
        self.enc3 = EncoderBlock(w[1], w[2], r[2])
        self.bottleneck = Stage(w[2], w[3], 2)
        self.dec3 = DecoderBlock(w[3], w[2], w[2])
        self.dec2 = DecoderBlock(w[2], w[1], w[1])
        self.dec1 = DecoderBlock(w[1], w[0], w[0])
        self.fuse = nn.Sequential(ConvUnit(w[0], w[0]), ResBlock(w[0]))
        self.mul_head = nn.Conv2d(w[0], 1, 3, padding=1)
        self.add_head = nn.Conv2d(w[0], 3, 3, padding=1)

    def predict_maps(
        self, low: Float[Tensor, "B 3 H W"], naka: Float[Tensor, "B 3 H W"]
    ) -> Tuple[Float[Tensor, "B 1 H W"], Float[Tensor, "B 3 H W"]]:
        """``(M_mul, M_add)`` at the input's resolution (sRGB [0, 1] inputs)."""
        if low.shape != naka.shape or low.ndim != 4 or low.shape[1] != 3:
            raise ValueError(f"low and naka must both be [B, 3, H, W], got {tuple(low.shape)} and {tuple(naka.shape)}")
        delta = naka - low
        x = torch.cat([low, naka, delta, standardize(low), standardize(naka), standardize(delta)], dim=1)
        x = self.stem(x)
        x, s1 = self.enc1(x)
        x, s2 = self.enc2(x)
        x, s3 = self.enc3(x)
        x = self.bottleneck(x)
        x = self.dec3(x, s3)
        x = self.dec2(x, s2)
        x = self.dec1(x, s1)
        x = self.fuse(x)
        mul = 1.0 + self.config.mul_range * torch.tanh(self.mul_head(x))
        add = self.config.add_range * torch.tanh(self.add_head(x))
        return mul, add

    def forward(self, low: Float[Tensor, "B 3 H W"], naka: Float[Tensor, "B 3 H W"]) -> Dict[str, Tensor]:
        """``{"enhanced": [B,3,H,W] in [0,1], "mul_map": [B,1,H,W], "add_map": [B,3,H,W]}``."""
        mul, add = self.predict_maps(low, naka)
        enhanced = apply_maps(naka, mul, add, self.config.lf_kernel, self.config.lf_sigma)
        return {"enhanced": enhanced, "mul_map": mul, "add_map": add}
