"""RealX3D by eye, 2D (docs/real-scenes.md): one training view per scene, columns low | Naka | Naka +
shipped network (its own colour) | + capture chroma | + scene exposure as a power curve | + scene
exposure as a linear-light gain (the default), at 1/4 size, and each scene's mean brightness after each
stage over every 5th training view. Run from the repository root:
    .venv/bin/python docs/experiments/realx3d_exposure_sheet.py
"""

import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.exposure import apply_gain, apply_gamma, lift_gain, lift_gamma, scene_mean
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.sheet import contact_sheet

torch.set_grad_enabled(False)
D = Path(__file__).resolve().parents[3] / "shared" / "data" / "realx3d"
OUT = Path(__file__).resolve().parents[1] / "img" / "realx3d_exposure_sheet.jpg"
naka = Enhancer(EnhanceConfig(correction="none", chroma="network", exposure="none", use_cache=False))
net = Enhancer(EnhanceConfig(chroma="network", exposure="none", use_cache=False))
chroma = Enhancer(EnhanceConfig(exposure="none", use_cache=False))


def quarter(path: Path) -> torch.Tensor:
    im = torch.from_numpy(read_rgb(path)).permute(2, 0, 1)[None]
    return torch.nn.functional.interpolate(im, scale_factor=0.25, mode="area")[0].permute(1, 2, 0).contiguous()


rows, table = [], []
for tj in sorted(D.glob("*/transforms_train.json")):
    frames = json.load(open(tj))["frames"][::5]
    low = [quarter(tj.parent / f["file_path"]) for f in frames]
    n = naka.enhance_images(low, description=f"{tj.parent.name} naka")
    c = net.enhance_images(low, description=f"{tj.parent.name} net")
    h = chroma.enhance_images(low, description=f"{tj.parent.name} capture chroma")
    g, gain = lift_gamma(h), lift_gain(h)
    e, eg = apply_gamma(h, g), apply_gain(h, gain)
    k = len(low) // 2
    rows.append([im[k].numpy() for im in (low, n, c, h, e, eg)])
    std = (
        float(np.mean([float(im.mean(-1).std()) for im in e])),
        float(np.mean([float(im.mean(-1).std()) for im in eg])),
    )
    table.append(
        (
            tj.parent.name,
            scene_mean(low),
            scene_mean(n),
            scene_mean(c),
            scene_mean(h),
            g,
            scene_mean(e),
            gain,
            scene_mean(eg),
            *std,
        )
    )
Image.fromarray(contact_sheet(rows, max_width=320)).save(OUT, quality=88)
print(
    "| scene | low | Naka | + network | + capture chroma | power `g` | + power | gain `k` | + gain (default) "
    "| contrast (s.d.) power / gain |"
)
print("|---|---|---|---|---|---|---|---|---|---|")
for name, *v in table:
    print(
        f"| {name} | {v[0]:.3f} | {v[1]:.3f} | {v[2]:.3f} | {v[3]:.3f} | {v[4]:.2f} | {v[5]:.3f} | {v[6]:.2f} "
        f"| {v[7]:.3f} | {v[8]:.3f} / {v[9]:.3f} |"
    )
print(f"wrote {OUT}")
