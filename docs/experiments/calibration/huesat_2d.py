"""Hue- and saturation-dependent calibration candidates on BlueHawaii, 2D, scored per hue family (issue 79).

Reads ``outputs/calibration/bluehawaii_stages.pt`` (``stages_2d.py``). Scored: the 10 views no fit used (every third,
0003 ... 0030); fits use the other 20. "Held-out blues": pixels whose normal photo is a saturated blue (HSV hue
190-260 degrees, saturation > 0.45, value > 0.12: the barrels and the blue signs), left out of every fit marked
"blues out" and scored on their own. Hue families group chromatic pixels (saturation >= 0.25, value >= 0.08) by the
normal photo's hue: reds 315-25, yellows 25-80, greens 80-170, blues 170-260, magentas 260-315 degrees. Colour
error: mean per-pixel L1 of linear-light chromaticities, on views area-downscaled to 441 px.

    .venv/bin/python docs/experiments/calibration/huesat_2d.py            # the table
    .venv/bin/python docs/experiments/calibration/huesat_2d.py stages     # the held-out blues through the chain
"""

import math
import sys
import time

import kornia
import numpy as np
import torch
import torch.nn.functional as F

from naka_gs_plugin.enhance.exposure import srgb_to_linear
from naka_gs_plugin.enhance.profile import _area, apply_maps, fit_profile
from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.model.lpips import LazyLPIPS

torch.manual_seed(0)
data = torch.load("outputs/calibration/bluehawaii_stages.pt")
f = {k: [x.float() for x in v] for k, v in data.items() if k != "names"}
held = list(range(2, 30, 3))
pool = [i for i in range(30) if i not in held]
FAMILIES = {"reds": (315, 25), "yellows": (25, 80), "greens": (80, 170), "blues": (170, 260), "magentas": (260, 315)}


def hsv(x):
    t = kornia.color.rgb_to_hsv(x.reshape(-1, 3).t()[:, :, None])[..., 0]
    return t[0] * 180 / math.pi, t[1], t[2]


def blues_mask(ref):
    h, s, v = hsv(ref)
    return ((h > 190) & (h < 260) & (s > 0.45) & (v > 0.12)).reshape(ref.shape[:2])


def chromaticity(x):
    lin = srgb_to_linear(x.clamp(0, 1))
    return lin / lin.sum(-1, keepdim=True).clamp(min=1e-4)


def family_errors(out, ref):
    o, r = _area(out, 441), _area(ref, 441)
    err = (chromaticity(o) - chromaticity(r)).abs().sum(-1).reshape(-1)
    h, s, v = hsv(r)
    chromatic = (s >= 0.25) & (v >= 0.08)
    masks = {k: chromatic & (((h >= a) | (h < b)) if a > b else ((h >= a) & (h < b))) for k, (a, b) in FAMILIES.items()}
    masks["held-out blues"] = blues_mask(r).reshape(-1)
    return {k: (float(err[m].sum()), int(m.sum())) for k, m in masks.items()}


lpips = LazyLPIPS()


def score(render, name):
    rows, sums = [], {}
    with torch.no_grad():
        for i in held:
            out, ref = render(i).clamp(0, 1), f["ref"][i]
            a, b = out.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
            rows.append([psnr(a, b), float(kornia.metrics.ssim(a, b, 11).mean()), float(lpips(a, b))])
            for k, (s, n) in family_errors(out, ref).items():
                s0, n0 = sums.get(k, (0.0, 0))
                sums[k] = (s0 + s, n0 + n)
    m = np.mean(rows, 0)
    fam = " | ".join(f"{s / max(n, 1):.3f}" for s, n in sums.values())
    print(f"| {name} | {m[0]:.2f} | {m[1]:.3f} | {m[2]:.3f} | {fam} |", flush=True)
    return sums


def pairs(key, idx, blues_out):
    """Fit inputs at 512 px; a left-out pixel's reference is set to white, which fit_profile drops as clipped."""
    xs, ys = [], []
    for i in idx:
        x, y = _area(f[key][i], 512), _area(f["ref"][i], 512).clone()
        if blues_out:
            y[blues_mask(y)] = 1.0
        xs.append(x)
        ys.append(y)
    return xs, ys


def lut_apply(x, lut):
    """Residual 3D LUT ``[3, D, D, D]`` (indexed blue, green, red) at sRGB ``x`` ``[N, 3]``, trilinear."""
    grid = (x.clamp(0, 1) * 2 - 1)[None, :, None, None, :]
    return F.grid_sample(lut[None], grid, mode="bilinear", align_corners=True)[0, :, :, 0, 0].t()


def fit_lut(x, y, size, lam, steps=1500, batch=16384, seed=0):
    """A residual LUT after the profile: Huber 0.1 in sRGB plus ``lam`` x the mean squared difference of neighbouring
    cells (smoothness; cells no pixel reaches follow their neighbours)."""
    gen = torch.Generator().manual_seed(seed)
    keep = y.max(1).values < 0.98
    x, y = x[keep], y[keep]
    lut = torch.zeros(3, size, size, size, requires_grad=True)
    opt = torch.optim.Adam([lut], lr=0.01)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    for _ in range(steps):
        idx = torch.randint(len(x), (batch,), generator=gen)
        smooth = sum((lut.diff(dim=k) ** 2).mean() for k in (1, 2, 3))
        loss = F.huber_loss(x[idx] + lut_apply(x[idx], lut), y[idx], delta=0.1) + lam * smooth
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return lut.detach()


def huesat_apply(x, table):
    """A DNG-style HueSatMap ``[3, S, H]`` (hue shift in radians, log saturation gain, log value gain over
    saturation x hue, hue circular), bilinear, at sRGB ``x`` ``[N, 3]``."""
    t = kornia.color.rgb_to_hsv(x.clamp(0, 1).t()[:, :, None])[..., 0].t()
    wrapped = torch.cat([table, table[:, :, :1]], 2)
    grid = torch.stack([t[:, 0] / math.pi - 1, t[:, 1] * 2 - 1], -1)[None, :, None, :]
    p = F.grid_sample(wrapped[None], grid, mode="bilinear", align_corners=True)[0, :, :, 0].t()
    h = torch.remainder(t[:, 0] + p[:, 0], 2 * math.pi)
    s, v = (t[:, 1] * p[:, 1].exp()).clamp(0, 1), (t[:, 2] * p[:, 2].exp()).clamp(0, 1)
    return kornia.color.hsv_to_rgb(torch.stack([h, s, v], 1).t()[:, :, None])[..., 0].t()


def fit_huesat(x, y, lam, hues=24, sats=9, steps=1500, batch=16384, seed=0):
    gen = torch.Generator().manual_seed(seed)
    keep = y.max(1).values < 0.98
    x, y = x[keep], y[keep]
    table = torch.zeros(3, sats, hues, requires_grad=True)
    opt = torch.optim.Adam([table], lr=0.01)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    for _ in range(steps):
        idx = torch.randint(len(x), (batch,), generator=gen)
        wrapped = torch.cat([table, table[:, :, :1]], 2)
        smooth = (wrapped.diff(dim=2) ** 2).mean() + (table.diff(dim=1) ** 2).mean()
        loss = F.huber_loss(huesat_apply(x[idx], table), y[idx], delta=0.1) + lam * smooth
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return table.detach()


def flat(x):
    return torch.cat([v.reshape(-1, 3) for v in x])


if sys.argv[1:] == ["stages"]:
    print("| view | stage | held-out blues, mean sRGB | their linear chromaticity | dark neutrals, mean sRGB |")
    print("|---|---|---|---|---|")
    for i in held[:3]:
        r = _area(f["ref"][i], 441)
        m = blues_mask(r)
        h, s, v = hsv(r)
        neutral = ((s < 0.15) & (v < 0.3)).reshape(m.shape)
        for k in ("low", "naka", "net", "chroma", "tone", "ref"):
            x = _area(f[k][i], 441)
            lin = srgb_to_linear(x[m]).mean(0)
            cells = [", ".join(f"{float(a):.4f}" for a in t) for t in (x[m].mean(0), lin / lin.sum(), x[neutral].mean(0))]
            print(f"| {data['names'][i]} | {k} | " + " | ".join(cells) + " |")
    sys.exit()

print("| candidate (10 unseen views) | PSNR | SSIM | LPIPS | " + " | ".join([*FAMILIES, "held-out blues"]) + " |")
print("|---|---|---|---|" + "---|" * (len(FAMILIES) + 1))
score(lambda i: f["tone"][i], "the chain, no profile")
for blues_out in (False, True):
    tag = "blues out" if blues_out else "all pixels"
    xs, ys = pairs("tone", pool, blues_out)
    curves, matrix, _ = fit_profile(xs, ys)
    sums = score(lambda i: apply_maps(f["tone"][i], curves, matrix), f"{tag}: profile (curves + matrix)")
    x, y = flat(xs), flat(ys)
    px = apply_maps(x, curves, matrix)
    for size, lam in ((17, 1.0), (33, 0.3)):
        t = time.perf_counter()
        lut = fit_lut(px, y, size, lam)
        sec = time.perf_counter() - t
        score(
            lambda i: (lambda o: o + lut_apply(o.reshape(-1, 3), lut).reshape(o.shape))(apply_maps(f["tone"][i], curves, matrix)),
            f"{tag}: profile + LUT {size}^3, smoothness {lam} ({sec:.0f} s)",
        )
    if blues_out:
        t = time.perf_counter()
        table = fit_huesat(px, y, 0.1)
        sec = time.perf_counter() - t
        score(
            lambda i: huesat_apply(apply_maps(f["tone"][i], curves, matrix).reshape(-1, 3), table).reshape(f["tone"][i].shape),
            f"{tag}: profile + HueSatMap 24x9, smoothness 0.1 ({sec:.0f} s)",
        )
print("pixels per family (10 views at 441 px):", {k: n for k, (_, n) in sums.items()})
