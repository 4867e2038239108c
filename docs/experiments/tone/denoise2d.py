"""2D probe, dropped (docs/real-scenes.md): OpenCV non-local means on the enhanced targets, strength a
multiple of the noise level estimated by Immerkaer's method; hold-out weights, LOM test views.
    .venv/bin/python docs/experiments/tone/denoise2d.py bike chair shrub sofa
"""

import sys

import cv2
import numpy as np
import torch
from lom2d import enhanced, scores, truths

from naka_gs_plugin.enhance.exposure import apply_gamma

torch.set_grad_enabled(False)
G = dict(bike=0.703, chair=1.0, shrub=0.925, sofa=1.0)


def sigma_est(u8):
    # Immerkaer (1996): noise s.d. from a Laplacian-difference mask, on the grey image, in [0,255]
    g = cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY).astype(np.float64)
    M = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], float)
    conv = cv2.filter2D(g, -1, M)[1:-1, 1:-1]
    H, W = g.shape
    return np.sqrt(np.pi / 2) * np.abs(conv).sum() / (6 * (W - 2) * (H - 2))


def nlm(im, k):
    u8 = (im.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    s = sigma_est(u8)
    out = cv2.fastNlMeansDenoisingColored(u8, None, k * s, k * s, 7, 21)
    return torch.from_numpy(out.astype(np.float32) / 255), s


KS = [0.5, 1.0, 1.5, 2.0]
tot = {}
for scene in sys.argv[1:]:
    targets = apply_gamma(enhanced(scene, "test"), G[scene])
    cands, sig = {"target": targets}, []
    for k in KS:
        out = [nlm(t, k) for t in targets]
        cands[f"nlm{k}"], sig = [o[0] for o in out], [o[1] for o in out]
    print(scene, "sigma_est", " ".join(f"{x:.2f}" for x in sig))
    for key, ims in cands.items():
        m = scores(ims, truths(scene))
        tot.setdefault(key, []).append(m)
        print(f"{scene} {key}: {m[0]:.2f} / {m[1]:.3f}")
for key, v in tot.items():
    m = np.mean(v, 0)
    print(f"MEAN {key}: {m[0]:.2f} / {m[1]:.3f}")
