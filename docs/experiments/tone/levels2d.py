"""2D probe, dropped (docs/real-scenes.md): a black point ("levels") mapping the scene's 1 % luminance
quantile to that of normal-light photos, before or after the exposure curve; hold-out weights, LOM test views.
    .venv/bin/python docs/experiments/tone/levels2d.py bike chair shrub sofa
"""

import json
import sys
from pathlib import Path

import kornia
import numpy as np
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.checkpoint import load_correction
from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.correction import CorrectionRunner
from naka_gs_plugin.enhance.exposure import apply_gamma, lift_gamma
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.metrics import psnr

torch.set_grad_enabled(False)
W = torch.tensor([0.2126, 0.7152, 0.0722])


def enhance(runner, low):
    naka = naka_enhance(low, 0.05)
    enh = runner(low.permute(2, 0, 1)[None], naka.permute(2, 0, 1)[None])["enhanced"][0].permute(1, 2, 0)
    return capture_chroma(enh, low)


def qlum(ims, q):
    L = torch.cat([(im @ W).reshape(-1)[::7] for im in ims])
    return float(torch.quantile(L, q))


def levels(ims, b, t):
    if b <= t:
        return list(ims)
    return [((im - b) / (1 - b) * (1 - t) + t).clamp(0, 1) for im in ims]


tot = {}
for scene in sys.argv[1:]:
    root = Path("../shared/data/lom") / scene
    runner = CorrectionRunner(load_correction(f"outputs/correction-loo/{scene}/best.pt"), "auto")

    def ld(split):
        return [
            torch.from_numpy(read_rgb(root / "low" / Path(f["file_path"]).name))
            for f in json.loads((root / f"transforms_{split}.json").read_text())["frames"]
        ]

    names = [Path(f["file_path"]).name for f in json.loads((root / "transforms_test.json").read_text())["frames"]]
    tr = [enhance(runner, lo) for lo in ld("train")]
    te = [enhance(runner, lo) for lo in ld("test")]
    truth = [torch.from_numpy(read_rgb(root / "high" / n)) for n in names]
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
        sc = [
            (psnr(im, tt), float(kornia.metrics.ssim(im.permute(2, 0, 1)[None], tt.permute(2, 0, 1)[None], 11).mean()))
            for im, tt in zip(ims, truth)
        ]
        m = np.mean(sc, 0)
        tot.setdefault(key, []).append(m)
        print(
            f"  {key:18s} {m[0]:.2f} / {m[1]:.3f}  q01 {qlum(ims, 0.01):.3f} std {float(torch.stack([(i @ W).std() for i in ims]).mean()):.3f}",
            flush=True,
        )
for key, v in tot.items():
    m = np.mean(v, 0)
    print(f"MEAN {key:18s} {m[0]:.2f} / {m[1]:.3f}")
