"""2D probe, dropped (docs/real-scenes.md): a black point ("levels") mapping the scene's 1 % luminance
quantile to that of normal-light photos, before or after the exposure curve; hold-out weights, LOM test views.
    .venv/bin/python docs/experiments/tone/levels2d.py bike chair shrub sofa
"""

import sys

import numpy as np
import torch
from lom2d import enhanced, scores, truths

from naka_gs_plugin.enhance.exposure import apply_gamma, lift_gamma

torch.set_grad_enabled(False)
W = torch.tensor([0.2126, 0.7152, 0.0722])


def qlum(ims, q):
    L = torch.cat([(im @ W).reshape(-1)[::7] for im in ims])
    return float(torch.quantile(L, q))


def levels(ims, b, t):
    if b <= t:
        return list(ims)
    return [((im - b) / (1 - b) * (1 - t) + t).clamp(0, 1) for im in ims]


tot = {}
for scene in sys.argv[1:]:
    tr, te, truth = enhanced(scene, "train"), enhanced(scene, "test"), truths(scene)
    b = qlum(tr, 0.01)
    g0 = lift_gamma(tr)
    variants = {"current": apply_gamma(te, g0)}
    for t in (0.095, 0.15):
        trl = levels(tr, b, t)
        g = lift_gamma(trl)
        variants[f"levels{t}>exp"] = apply_gamma(levels(te, b, t), g)
        trg = apply_gamma(tr, g0)
        b2 = qlum(trg, 0.01)
        variants[f"exp>levels{t}"] = levels(apply_gamma(te, g0), b2, t)
    print(scene, f"b={b:.3f} g0={g0:.3f}")
    for key, ims in variants.items():
        m = scores(ims, truth)
        tot.setdefault(key, []).append(m)
        print(
            f"  {key:18s} {m[0]:.2f} / {m[1]:.3f}  q01 {qlum(ims, 0.01):.3f} std {float(torch.stack([(i @ W).std() for i in ims]).mean()):.3f}",
            flush=True,
        )
for key, v in tot.items():
    m = np.mean(v, 0)
    print(f"MEAN {key:18s} {m[0]:.2f} / {m[1]:.3f}")
