"""2D probe (docs/real-scenes.md): exposure by the power curve against a linear-light gain with highlight
knees 1 (clip), 0.8 and 0.6; parameters from every other training view, scored on the LOM test views.
    .venv/bin/python docs/experiments/tone/gain2d.py bike shrub
"""

import sys

import kornia
import torch
from lom2d import enhanced, scores, truths

from naka_gs_plugin.enhance.exposure import METERED_TARGET, _linear, apply_gamma, lift_gamma

torch.set_grad_enabled(False)
W = torch.tensor([0.2126, 0.7152, 0.0722])
lin = kornia.color.rgb_to_linear_rgb
enc = kornia.color.linear_rgb_to_rgb


def CHW(x):
    return x.permute(2, 0, 1)


def HWC(x):
    return x.permute(1, 2, 0)


def shoulder(u, knee):
    if knee >= 1:
        return u.clamp(0, 1)
    s = 1 - knee
    return torch.where(u <= knee, u, knee + s * (1 - torch.exp(-(u - knee) / s)))


def gain(im, k, knee):
    return HWC(enc(shoulder(lin(CHW(im.clamp(0, 1))) * k, knee).clamp(0, 1)))


def find_k(ims, knee):
    goal = float(_linear(torch.full((1, 3), METERED_TARGET))[0, 0])
    sample = torch.cat([im.reshape(-1, 3)[::7] for im in ims]).clamp(0, 1)

    def L(k):
        return float((shoulder(lin(sample.T[:, :, None])[:, :, 0].T * k, knee) @ W).mean())

    if L(1.0) >= goal:
        return 1.0
    lo, hi = 1.0, 64.0
    for _ in range(40):
        mid = (lo * hi) ** 0.5
        if L(mid) < goal:
            lo = mid
        else:
            hi = mid
    return lo


tot = {}
for scene in sys.argv[1:]:
    tr, te, truth = enhanced(scene, "train")[::2], enhanced(scene, "test"), truths(scene)
    g0 = lift_gamma(tr)
    variants = {"power(current)": apply_gamma(te, g0)}
    for knee in (1.0, 0.8, 0.6):
        k = find_k(tr, knee)
        variants[f"gain knee{knee} k={k:.2f}"] = [gain(im, k, knee) for im in te]
    print(scene, f"g0={g0:.3f}")
    for key, ims in variants.items():
        m = scores(ims, truth)
        tot.setdefault(key.split(" k=")[0], []).append(m)
        print(
            f"  {key:26s} {m[0]:.2f} / {m[1]:.3f} std {float(torch.stack([(i @ W).std() for i in ims]).mean()):.3f} mean {float(torch.stack([i.mean() for i in ims]).mean()):.3f}",
            flush=True,
        )
    print(
        f"  truth std {float(torch.stack([(i @ W).std() for i in truth]).mean()):.3f} mean {float(torch.stack([i.mean() for i in truth]).mean()):.3f}"
    )
