"""2D lever record (docs/real-scenes.md): one exposure curve per scene after the correction network.

The enhanced views of a scene are raised to one power ``g`` (per pixel and channel, sRGB [0, 1]) chosen
so that their mean is middle grey (0.18 linear = 0.461 sRGB): average-metering auto-exposure, applied
once per scene so every view keeps the same tone curve. Scored with the shipped weights on the LOM test
views (``g`` from the scene's enhanced *training* views, as the datamanager would) and LOL eval15 (each
image its own scene); prints the RealX3D output means. Run from the repository root:
    .venv/bin/python docs/experiments/exposure.py
"""
import json
from pathlib import Path

import kornia
import numpy as np
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS, load_correction
from naka_gs_plugin.enhance.correction import CorrectionRunner
from naka_gs_plugin.enhance.naka import naka_enhance

torch.set_grad_enabled(False)
D = Path(__file__).resolve().parents[3] / "shared" / "data"
runner = CorrectionRunner(load_correction(DEFAULT_WEIGHTS), "auto")
GREY = 0.4613


def load(p):
    return torch.from_numpy(read_rgb(p))


def enhance(low, gain=1.0):
    low = (low * gain).clamp(0, 1)
    n = naka_enhance(low, 0.05)
    return runner(low.permute(2, 0, 1)[None], n.permute(2, 0, 1)[None])["enhanced"][0].permute(1, 2, 0)


def solve_gamma(views, target=GREY, lift_only=False):
    sample = torch.cat([v.flatten()[::5] for v in views]).double().clamp(1e-6, 1)
    lo, hi = 0.05, 20.0
    for _ in range(50):
        g = (lo * hi) ** 0.5
        if sample.pow(g).mean() > target:
            lo = g
        else:
            hi = g
    g = (lo * hi) ** 0.5
    return min(g, 1.0) if lift_only else g


def score(pred, gt):
    mse = ((pred - gt) ** 2).mean().item()
    ssim = kornia.metrics.ssim(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], 11).mean().item()
    return 10 * np.log10(1 / mse), ssim


rows = {"none": [], "grey": [], "grey-lift": []}
for tj in sorted((D / "lom").glob("*/transforms_test.json")):
    root = tj.parent
    train = [enhance(load(root / "low" / Path(f["file_path"]).name)) for f in json.load(open(root / "transforms_train.json"))["frames"]]
    g = solve_gamma(train)
    gl = min(g, 1.0)
    print(f"lom/{root.name}: train enhanced mean {np.mean([t.mean().item() for t in train]):.3f} gamma {g:.3f}", flush=True)
    for f in json.load(open(tj))["frames"]:
        gt = load(root / f["file_path"])
        out = enhance(load(root / "low" / Path(f["file_path"]).name))
        for k, gg in (("none", 1.0), ("grey", g), ("grey-lift", gl)):
            o = out.clamp(0, 1) ** gg
            rows[k].append(("lom", *score(o, gt), o.mean().item(), gt.mean().item()))
for gtp in sorted((D / "lol/eval/high").glob("*"))[:15]:
    gt = load(gtp)
    out = enhance(load(D / "lol/eval/low" / gtp.name))
    g = solve_gamma([out])
    for k, gg in (("none", 1.0), ("grey", g), ("grey-lift", min(g, 1.0))):
        o = out.clamp(0, 1) ** gg
        rows[k].append(("lol", *score(o, gt), o.mean().item(), gt.mean().item()))
for k, v in rows.items():
    for s in ("lom", "lol"):
        a = np.array([x[1:] for x in v if x[0] == s])
        print(f"{k:10s} {s}: PSNR {a[:, 0].mean():.3f} SSIM {a[:, 1].mean():.4f} out mean {a[:, 2].mean():.3f} gt mean {a[:, 3].mean():.3f}", flush=True)
for tj in sorted((D / "realx3d").glob("*/transforms_train.json")):
    fr = json.load(open(tj))["frames"][::10]
    outs = []
    for f in fr:
        low = load(tj.parent / f["file_path"]).permute(2, 0, 1)[None]
        low = torch.nn.functional.interpolate(low, scale_factor=0.25, mode="area")[0].permute(1, 2, 0)
        outs.append(enhance(low))
    g = solve_gamma(outs)
    print(f"realx3d/{tj.parent.name:12s} out mean {np.mean([o.mean().item() for o in outs]):.3f} gamma {g:.3f}", flush=True)
