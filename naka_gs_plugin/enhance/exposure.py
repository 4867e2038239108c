"""Scene exposure: one tone curve that lifts a too-dark enhanced scene to a normal photo's exposure.

The correction network leaves the exposure about where the Naka stretch puts it, and the stretch takes
its maximum from the brightest pixels: in captures with lamps or highlights (RealX3D) the enhanced views
are far darker than normal-light photos. Like a camera's average metering, the scene's *metered level*,
the mean luminance in linear light (sRGB-encoded to compare with pixel values), is brought to that of
normal-light photos by one curve shared by every view (a per-view curve would give each view its own
appearance). Scenes already at or above the target are left alone: a bright night scene is not darkened.
The curve is what a longer exposure does: every linear value times one factor ``k >= 1``, with a soft
shoulder above :data:`KNEE` so highlights roll off to white instead of clipping; contrast and the blacks
stay where the capture has them (a power curve on sRGB values, which flattens the views, lost on the LOM
protocol: records/2026-11-27-levers.md).

Metering in linear light is what tells a dark-toned scene from an under-exposed one: a few bright areas
(sky through foliage) carry a large share of the light, so a scene of dark leaves under a bright sky
meters as exposed although its mean sRGB value is low. On LOM's normal-light photos the mean sRGB value
ranges 0.36-0.54 between scenes and the metered level only 0.50-0.58 (docs/real-scenes.md); metering the
mean sRGB value instead lost on the protocol.

Images are sRGB-encoded in [0, 1], channel-last ``[H, W, 3]``.
"""

from __future__ import annotations

from typing import List, Sequence

import torch
from jaxtyping import Float
from torch import Tensor

METERED_TARGET = 0.505
"""Metered level (sRGB encoding of the mean linear luminance) of LOL's 500 normal-light photos (mean;
s.d. 0.10, median 0.505): the exposure a normal photo of an indoor scene has."""

MAX_GAIN = 16.0
"""Strongest gain allowed (4 stops): a nearly black scene (noise only) is not stretched into a grey wash."""

KNEE = 0.8
"""Linear level above which ``gain`` compresses instead of clipping: ``knee + (1 - knee) (1 - exp(-(u -
knee) / (1 - knee)))`` for ``u = k x > knee``, continuous with slope 1 at the knee and approaching 1 (a
film-like shoulder); 0.8 linear is 0.91 in sRGB, so mid-tones are a pure gain."""

LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB luminance weights of linear R, G, B."""


def srgb_to_linear(srgb: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
    """sRGB [0, 1] -> linear RGB, channel-last (kornia's transfer function, which wants channels first)."""
    # Imported here: every ns-* command imports the method config, hence this module, and stays light.
    import kornia

    as_image = srgb.reshape(-1, 3).T[:, :, None]  # [3, N, 1]
    return kornia.color.rgb_to_linear_rgb(as_image)[:, :, 0].T.reshape(srgb.shape)


def _linear_luminance(linear: Float[Tensor, "N 3"]) -> float:
    """Mean luminance of linear RGB pixels."""
    return float((linear @ linear.new_tensor(LUMA)).mean())


def _luminance(srgb: Float[Tensor, "N 3"]) -> float:
    """Mean linear luminance of sRGB pixels."""
    return _linear_luminance(srgb_to_linear(srgb))


def linear_to_srgb(linear: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
    """Linear RGB [0, 1] -> sRGB, channel-last (the inverse of :func:`srgb_to_linear`)."""
    import kornia

    as_image = linear.reshape(-1, 3).T[:, :, None]  # [3, N, 1]
    return kornia.color.linear_rgb_to_rgb(as_image)[:, :, 0].T.reshape(linear.shape)


def _encode(linear: float) -> float:
    """Linear [0, 1] -> sRGB [0, 1] of one grey level."""
    return float(linear_to_srgb(torch.full((1, 3), linear, dtype=torch.float64))[0, 0])


def metered_level(images: Sequence[Float[Tensor, "H W 3"]]) -> float:
    """The scene's exposure as a camera's average metering reads it: the sRGB encoding of the mean Rec. 709
    luminance in linear light, in [0, 1]."""
    return _encode(_luminance(_sample(images, 1)))


def _sample(images: Sequence[Float[Tensor, "H W 3"]], stride: int) -> Float[Tensor, "N 3"]:
    """Every ``stride``-th pixel of every view, float64 in [0, 1]."""
    return torch.cat([im.reshape(-1, 3)[::stride] for im in images]).double().clamp(0.0, 1.0)


def lift_gain(images: Sequence[Float[Tensor, "H W 3"]], target: float = METERED_TARGET, stride: int = 7) -> float:
    """The linear-light factor ``k`` in ``[1, MAX_GAIN]`` for which ``apply_gain(images, k)`` meters at
    ``target`` (1 when the scene already meters at least ``target``). Bisection on every ``stride``-th pixel."""
    if not 0.0 < target < 1.0:
        raise ValueError(f"exposure target must be in (0, 1), got {target!r}")
    goal = float(srgb_to_linear(torch.full((1, 3), target))[0, 0])
    linear = srgb_to_linear(_sample(images, stride))
    if linear.numel() == 0 or _linear_luminance(linear) >= goal:
        return 1.0
    # Each channel's linear values sorted once, with prefix sums: at a gain the pixels below the knee meter as
    # that gain times their sum, and only those above it go through the shoulder. The same metering as
    # ``_luminance(_gain(sample, gain))`` up to float64 rounding (that one decodes its own sRGB encoding again).
    channels = [linear[:, c].sort().values for c in range(3)]
    prefix = [torch.cat([v.new_zeros(1), v.cumsum(0)]) for v in channels]

    def metered(gain: float) -> float:
        total = 0.0
        for weight, values, sums in zip(LUMA, channels, prefix):
            below = int(torch.searchsorted(values, KNEE / gain, right=True))
            total += weight * (gain * float(sums[below]) + float(_shoulder(values[below:] * gain).sum()))
        return total / len(linear)

    weakest, strongest = 1.0, MAX_GAIN
    if metered(strongest) <= goal:
        return strongest
    for _ in range(40):
        mid = 0.5 * (weakest + strongest)
        if metered(mid) < goal:
            weakest = mid
        else:
            strongest = mid
    return 0.5 * (weakest + strongest)


def _shoulder(u: Tensor) -> Tensor:
    """Identity up to :data:`KNEE`, then an exponential roll-off towards 1 (see :data:`KNEE`)."""
    span = 1.0 - KNEE
    return torch.where(u <= KNEE, u, KNEE + span * -torch.expm1(-(u - KNEE).clamp_min(0.0) / span))


def _gain(srgb: Float[Tensor, "*batch 3"], gain: float) -> Float[Tensor, "*batch 3"]:
    """sRGB [0, 1] -> times ``gain`` in linear light, shoulder, -> sRGB [0, 1]."""
    return linear_to_srgb(_shoulder(srgb_to_linear(srgb.clamp(0.0, 1.0)) * gain)).clamp(0.0, 1.0)


def apply_gain(images: Sequence[Float[Tensor, "H W 3"]], gain: float) -> List[Float[Tensor, "H W 3"]]:
    """Every view times ``gain`` in linear light with the highlight shoulder; the inputs themselves when
    ``gain == 1``."""
    if gain == 1.0:
        return list(images)
    return [_gain(im, gain) for im in images]
