"""2D probe, dropped (docs/real-scenes.md): OpenCV non-local means on the enhanced targets, strength a
multiple of the noise level estimated by Immerkaer's method; hold-out weights, LOM test views.
    .venv/bin/python docs/experiments/tone/denoise2d.py bike chair shrub sofa
"""

import json
import sys
from pathlib import Path

import cv2
import kornia
import numpy as np
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.checkpoint import load_correction
from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.correction import CorrectionRunner
from naka_gs_plugin.enhance.exposure import apply_gamma
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.metrics import psnr

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
    root = Path("../shared/data/lom") / scene
    runner = CorrectionRunner(load_correction(f"outputs/correction-loo/{scene}/best.pt"), "auto")
    rows = {}
    for i, frame in enumerate(json.loads((root / "transforms_test.json").read_text())["frames"]):
        name = Path(frame["file_path"]).name
        low = torch.from_numpy(read_rgb(root / "low" / name))
        naka = naka_enhance(low, 0.05)
        enh = runner(low.permute(2, 0, 1)[None], naka.permute(2, 0, 1)[None])["enhanced"][0].permute(1, 2, 0)
        tgt = apply_gamma([capture_chroma(enh, low)], G[scene])[0]
        truth = torch.from_numpy(read_rgb(root / "high" / name))
        cands = {"target": tgt}
        sig = None
        for k in KS:
            cands[f"nlm{k}"], sig = nlm(tgt, k)
        for key, im in cands.items():
            ss = float(kornia.metrics.ssim(im.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], 11).mean())
            rows.setdefault(key, []).append((psnr(im, truth), ss))
        print(scene, i, "sigma_est %.2f" % sig, flush=True)
    for key, v in rows.items():
        m = np.mean(v, 0)
        tot.setdefault(key, []).append(m)
        print(f"{scene} {key}: {m[0]:.2f} / {m[1]:.3f}")
for key, v in tot.items():
    m = np.mean(v, 0)
    print(f"MEAN {key}: {m[0]:.2f} / {m[1]:.3f}")
