"""A camera profile: how one camera renders a dark frame, learnt once from a few dark/normal pairs.

The profile maps the enhancement chain's output (sRGB [0, 1], after the Naka response, the correction network,
capture chroma and capture tone) onto the camera's normal-light rendering of the same view, per pixel:

1. a monotone curve per channel, from the enhanced sRGB value to linear light (level-dependent gains: the dark
   JPEG loses its red difference in the shadows, not in the highlights);
2. a 3x3 colour matrix in linear light (the cross-channel part of the cast), then the sRGB encoding.

It is fitted robustly (a Huber loss in sRGB: squared errors, as PSNR weighs them, up to :data:`HUBER_DELTA`; what a
pair does not share beyond it, a moved object or a lamp, pulls no harder) on area-downscaled pairs, in seconds, by :func:`fit_profile`; :func:`apply_profile` is the view stage's maths. A profile is a small JSON file
(``naka-gs-calibrate`` writes it) that also records the chain it was fitted after and the pairs' exposure ratios.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Sequence

import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.enhance.exposure import linear_to_srgb, srgb_to_linear
from naka_gs_plugin.errors import UserError

PROFILE_FORMAT = "naka-gs-camera-profile"
PROFILE_VERSION = 1
KNOTS = 17
"""Curve knots, evenly spaced in the enhanced sRGB value: a step of 1/16 (16 codes of 255)."""
FIT_LONG_SIDE = 512
"""Pairs are area-downscaled to this longer side before fitting: it averages the dark frame's noise and a pair's
sub-pixel misalignment, and keeps the fit to seconds."""


HUBER_DELTA = 0.1
"""Residuals beyond this (sRGB, 25 codes) count linearly in the fit."""


class CameraProfileError(UserError, ValueError):
    """A profile file that cannot be used (missing, not a profile, damaged); the message names it and the fix."""


@dataclass
class CameraProfile:
    """The fitted maps (see the module docstring) and what they were fitted on."""

    curves: List[List[float]]
    """``[3][KNOTS]`` linear-light outputs at the knots ``k / (KNOTS - 1)`` of each channel's enhanced sRGB value."""
    matrix: List[List[float]]
    """``[3][3]`` colour matrix applied to the curves' linear RGB (row = output channel)."""
    chain: Dict[str, Any] = field(default_factory=dict)
    """The enhancement stages it was fitted after (their cache keys): a run with another chain is warned."""
    pairs: List[Dict[str, Any]] = field(default_factory=list)
    """Per calibration pair: name, exposure ratio, PSNR before and after the profile."""
    fit: Dict[str, Any] = field(default_factory=dict)
    """How the fit went: seconds, samples, loss."""

    def to_json(self) -> str:
        return json.dumps({"format": PROFILE_FORMAT, "version": PROFILE_VERSION, **asdict(self)}, indent=1)

    @classmethod
    def load(cls, path: Path, option: str = "--enhance.profile") -> "CameraProfile":
        """Read ``path``; a missing or damaged file raises one line naming ``option`` and the fix."""
        fix = f"pass {option} the .json file naka-gs-calibrate wrote, or leave {option} out"
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8-sig"))
        except FileNotFoundError:
            raise CameraProfileError(f"{option} {path}: no such file -- {fix}") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise CameraProfileError(f"{option} {path}: not a camera profile ({err}) -- {fix}") from None
        if not isinstance(data, dict) or data.get("format") != PROFILE_FORMAT:
            raise CameraProfileError(f"{option} {path}: not a camera profile -- {fix}")
        if data.get("version") != PROFILE_VERSION:
            raise CameraProfileError(
                f"{option} {path}: profile version {data.get('version')}, this naka-gs reads {PROFILE_VERSION} -- "
                "calibrate again with this version (naka-gs-calibrate PAIRS --out PROFILE)"
            )
        try:
            profile = cls(
                **{k: data[k] for k in ("curves", "matrix")},
                **{k: data.get(k, {} if k != "pairs" else []) for k in ("chain", "pairs", "fit")},
            )
            curves, matrix = profile.tensors()
        except (KeyError, TypeError, ValueError) as err:
            raise CameraProfileError(f"{option} {path}: damaged camera profile ({err}) -- {fix}") from None
        if (
            curves.shape != (3, KNOTS)
            or matrix.shape != (3, 3)
            or not (curves.isfinite().all() and matrix.isfinite().all())
        ):
            raise CameraProfileError(f"{option} {path}: damaged camera profile (curves or matrix malformed) -- {fix}")
        return profile

    def tensors(self) -> tuple[Float[Tensor, "3 K"], Float[Tensor, "3 3"]]:
        return torch.tensor(self.curves, dtype=torch.float32), torch.tensor(self.matrix, dtype=torch.float32)


def chain_key(stages: Sequence[Any]) -> Dict[str, Any]:
    """What a profile records of the view stages before it (their cache keys, as JSON values), leaving out the
    correction's inference mode: the modes agree to the quality bar, and which one runs depends on the CPU."""
    keys = [{k: v for k, v in stage.key().items() if k != "mode"} for stage in stages if stage.name != "profile"]
    return json.loads(json.dumps({"stages": keys}, default=str))


def _monotone(first: Float[Tensor, "3 1"], steps: Float[Tensor, "3 K-1"]) -> Float[Tensor, "3 K"]:
    """Curves from their fitted parameters: the first knot's value and the steps between knots, both through
    softplus, so every curve is positive and rising."""
    return torch.cumsum(torch.nn.functional.softplus(torch.cat([first, steps], 1)), 1)


def _curve(x: Float[Tensor, "*N 3"], curves: Float[Tensor, "3 K"]) -> Float[Tensor, "*N 3"]:
    """Piecewise-linear interpolation of each channel's curve at ``x`` (sRGB [0, 1]) -> linear light."""
    k = curves.shape[1] - 1
    pos = x.clamp(0, 1) * k
    lo = pos.floor().clamp(max=k - 1).long()
    frac = pos - lo
    flat = curves.t()  # [K, 3]: row = knot
    ch = torch.arange(3, device=x.device).expand_as(lo)
    return flat[lo, ch] * (1 - frac) + flat[lo + 1, ch] * frac


def apply_maps(
    image: Float[Tensor, "*N 3"], curves: Float[Tensor, "3 K"], matrix: Float[Tensor, "3 3"]
) -> Float[Tensor, "*N 3"]:
    """The profile's maths on sRGB [0, 1] values (channel-last): curves to linear light, matrix, sRGB encoding."""
    return linear_to_srgb((_curve(image, curves) @ matrix.t()).clamp(0, 1))


def apply_profile(image: Float[Tensor, "H W 3"], profile: CameraProfile) -> Float[Tensor, "H W 3"]:
    """``image`` (sRGB [0, 1]) as the profile's camera renders it at normal light (sRGB [0, 1], float32)."""
    return apply_maps(image.float(), *profile.tensors())


def _area(image: Float[Tensor, "H W 3"], long_side: int) -> Float[Tensor, "h w 3"]:
    """Area-average ``image`` so its longer side is at most ``long_side``."""
    h, w = image.shape[:2]
    f = max(1, math.ceil(max(h, w) / long_side))
    if f == 1:
        return image
    x = image.permute(2, 0, 1)[None, :, : h // f * f, : w // f * f]
    return torch.nn.functional.avg_pool2d(x, f)[0].permute(1, 2, 0)


def fit_profile(
    enhanced: Sequence[Float[Tensor, "H W 3"]],
    references: Sequence[Float[Tensor, "H W 3"]],
    steps: int = 600,
    batch: int = 4096,
    seed: int = 0,
) -> tuple[Float[Tensor, "3 K"], Float[Tensor, "3 3"], Dict[str, Any]]:
    """Fit the curves and matrix taking each ``enhanced`` view (sRGB [0, 1]) to its ``references`` photo (same
    size, aligned). Huber loss in sRGB on area-downscaled pixels, Adam on ``steps`` random batches of
    ``batch`` pixels (cosine learning rate); curves kept monotone by construction (cumulative softplus steps).
    Returns ``(curves, matrix, stats)``."""
    gen = torch.Generator().manual_seed(seed)
    xs, ys = [], []
    for e, r in zip(enhanced, references):
        xs.append(_area(e.float(), FIT_LONG_SIDE).reshape(-1, 3))
        ys.append(_area(r.float(), FIT_LONG_SIDE).reshape(-1, 3))
    x, y = torch.cat(xs), torch.cat(ys)
    # Clipped references carry no level: they would pull the curves down at the top.
    keep = y.max(dim=1).values < 0.98
    x, y = x[keep], y[keep]
    knots = torch.linspace(0, 1, KNOTS)
    start = srgb_to_linear(knots[:, None].expand(-1, 3))[:, 0].clamp(min=1e-6)
    # Parameters: the first knot's value and softplus steps between knots (monotone); identity start.
    base = torch.full((3, 1), math.log(math.expm1(max(float(start[0]), 1e-4))))
    steps0 = torch.log(torch.expm1((start[1:] - start[:-1]).clamp(min=1e-5)))
    first = base.clone().requires_grad_(True)
    inc = steps0.expand(3, -1).clone().requires_grad_(True)
    matrix = torch.eye(3).requires_grad_(True)
    opt = torch.optim.Adam([first, inc, matrix], lr=0.02)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    batch = min(len(x), batch)
    for _ in range(steps):
        idx = torch.randint(len(x), (batch,), generator=gen)
        out = apply_maps(x[idx], _monotone(first, inc), matrix)
        loss = torch.nn.functional.huber_loss(out, y[idx], delta=HUBER_DELTA)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        curves = _monotone(first, inc)
        final = float(torch.nn.functional.huber_loss(apply_maps(x, curves, matrix), y, delta=HUBER_DELTA))
    return curves.detach(), matrix.detach(), {"samples": int(len(x)), "steps": steps, "loss": final}
