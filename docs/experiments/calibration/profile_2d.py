"""Camera profiles fitted on some BlueHawaii pairs, scored on the 10 views none of them used (2D).

Reads ``outputs/calibration/bluehawaii_stages.pt`` (``stages_2d.py``). The 10 scored views are every third view
(0003, 0006, ..., 0030); profiles are fitted on N of the other 20 (evenly spread). ``after`` names the chain stage
the profile is fitted after: ``net`` (Naka + network), ``chroma`` (+ capture chroma), ``tone`` (+ capture tone, the
default chain). The first row is today's default (tone + the scene exposure step over all 30 views).

    .venv/bin/python docs/experiments/calibration/profile_2d.py [after=tone] [N ...]
"""

import sys
import time

import kornia
import numpy as np
import torch

from naka_gs_plugin.enhance.profile import CameraProfile, apply_profile, fit_profile
from naka_gs_plugin.enhance.stages import ExposureStage
from naka_gs_plugin.metrics import colour_error, psnr
from naka_gs_plugin.model.lpips import LazyLPIPS

torch.manual_seed(0)
data = torch.load("outputs/calibration/bluehawaii_stages.pt")
f = {k: [x.float() for x in v] for k, v in data.items() if k != "names"}
BATCH = int(next((a.split("=")[1] for a in sys.argv if a.startswith("batch=")), 4096))
held = list(range(2, 30, 3))
pool = [i for i in range(30) if i not in held]
lpips = LazyLPIPS()


def score(images, idx):
    rows = []
    for im, i in zip(images, idx):
        a, b = im.permute(2, 0, 1)[None].clamp(0, 1), f["ref"][i].permute(2, 0, 1)[None]
        with torch.no_grad():
            rows.append(
                [
                    psnr(a, b),
                    float(kornia.metrics.ssim(a, b, 11).mean()),
                    float(lpips(a, b)),
                    colour_error(im, f["ref"][i])["chroma_l1"],
                ]
            )
    return np.mean(rows, 0)


def show(name, s, extra=""):
    print(f"| {name} | {s[0]:.2f} | {s[1]:.3f} | {s[2]:.3f} | {s[3]:.3f} | {extra} |", flush=True)


args = sys.argv[1:]
after = next((a.split("=")[1] for a in args if a.startswith("after=")), "tone")
counts = [int(a) for a in args if a.isdigit()] or [3, 5, 10, 20]
print("| views scored: 10 unseen | PSNR | SSIM | LPIPS | chroma L1 | fit |")
print("|---|---|---|---|---|---|")
exposed = ExposureStage().apply_all([x for x in f["tone"]])
show("today's default (no profile)", score([exposed[i] for i in held], held))
for n in counts:
    use = [pool[int(round(j))] for j in np.linspace(0, len(pool) - 1, n)]
    t = time.perf_counter()
    curves, matrix, stats = fit_profile([f[after][i] for i in use], [f["ref"][i] for i in use], batch=BATCH)
    sec = time.perf_counter() - t
    prof = CameraProfile(curves=curves.tolist(), matrix=matrix.tolist())
    with torch.no_grad():
        out = [apply_profile(f[after][i], prof) for i in held]
    show(f"profile after {after}, {n} pairs", score(out, held), f"{sec:.1f} s, loss {stats['loss']:.4f}")
