"""2D lever record (docs/real-scenes.md): Naka sigma fixed at 0.05 vs adapted to the mean, shipped weights.

Scores Naka + network against the normal-light truth on the LOM test views (sigma = the scene's mean over
its training views) and LOL eval15 (sigma = the image's mean), and prints the mean output brightness
of every 10th RealX3D training view at 1/4 size. Run from the repository root:
    .venv/bin/python docs/experiments/naka_sigma.py
"""
import json, sys, glob, numpy as np, torch, kornia
from pathlib import Path
torch.set_grad_enabled(False)
from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS, load_correction
from naka_gs_plugin.enhance.correction import CorrectionRunner
from naka_gs_plugin.enhance.naka import naka_rushton, stretch_stats, linear_stretch
from naka_gs_plugin.data.images import read_rgb
D = Path(__file__).resolve().parents[3] / "shared" / "data"
runner = CorrectionRunner(load_correction(DEFAULT_WEIGHTS), "auto")
def load(p):
    return torch.from_numpy(read_rgb(p))
def enhance(low, sigma, pct=None):
    r = naka_rushton(low, sigma)
    lo, hi = stretch_stats(r)
    if pct is not None:
        hi = torch.quantile(r.flatten()[::7], pct)
    n = linear_stretch(r, lo, hi)
    out = runner(low.permute(2,0,1)[None], n.permute(2,0,1)[None])["enhanced"]
    return out[0].permute(1,2,0)
def score(pred, gt):
    mse = ((pred-gt)**2).mean().item()
    return 10*np.log10(1/mse), kornia.metrics.ssim(pred.permute(2,0,1)[None], gt.permute(2,0,1)[None], 11).mean().item()
variants = {"fixed0.05": lambda low, m: enhance(low, 0.05), "mean": lambda low, m: enhance(low, m),
            "0.5mean": lambda low, m: enhance(low, 0.5*m),"mean+p99": lambda low, m: enhance(low, m, 0.99)}
res = {k: [] for k in variants}
sets = []
for scene in sorted((D/"lom").glob("*/transforms_test.json")):
    tr = json.load(open(scene.parent/"transforms_train.json"))["frames"]
    smean = float(np.mean([load(scene.parent/f["file_path"]).mean().item() for f in tr]))
    for f in json.load(open(scene))["frames"]:
        gt = scene.parent/f["file_path"]; low = scene.parent/"low"/gt.name
        sets.append(("lom", load(low), load(gt), smean))
for gt in sorted((D/"lol/eval/high").glob("*"))[:15]:
    low = load(D/"lol/eval/low"/gt.name); sets.append(("lol", low, load(gt), low.mean().item()))
for name, low, gt, m in sets:
    for k, f in variants.items():
        out = f(low, m); res[k].append((name, *score(out, gt), out.mean().item(), gt.mean().item()))
for k, v in res.items():
    for s in ("lom", "lol"):
        a = np.array([x[1:] for x in v if x[0] == s])
        print(f"{k:10s} {s}: PSNR {a[:,0].mean():.3f} SSIM {a[:,1].mean():.4f} out mean {a[:,2].mean():.3f} gt mean {a[:,3].mean():.3f}")
# RealX3D brightness
for scene in sorted((D/"realx3d").glob("*/transforms_train.json")):
    fr = json.load(open(scene))["frames"][::10]
    lows = [torch.nn.functional.interpolate(load(scene.parent/f["file_path"]).permute(2,0,1)[None], scale_factor=0.25, mode="area")[0].permute(1,2,0) for f in fr]
    m = float(np.mean([l.mean().item() for l in lows]))
    line = f"{scene.parent.name:12s} low mean {m:.3f}"
    for k, f in variants.items():
        line += f" | {k} {np.mean([f(l, m).mean().item() for l in lows]):.3f}"
    print(line, flush=True)
