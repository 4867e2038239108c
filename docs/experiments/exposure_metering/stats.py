"""Per LOM scene: sRGB mean vs sRGB of the linear mean (what a camera's average metering sets) for the
dark capture, the hold-out network's output and the normal-light truth. Needs /tmp/exp/X.pt
(docs/experiments/capture_chroma/cache2d.py)."""

import torch
from kornia.color import rgb_to_linear_rgb

from naka_gs_plugin.enhance.chroma import capture_chroma


def lin(x):
    return rgb_to_linear_rgb(x.float().permute(2, 0, 1)[None])


def enc(v):  # sRGB encoding of a linear scalar
    return 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055


for scene in ("bike", "chair", "shrub", "sofa"):
    d = torch.load(f"/tmp/exp/{scene}.pt")
    row = {}
    for key in ("low", "net", "cap", "truth"):
        ims = [capture_chroma(v["net"].float(), v["low"].float()) if key == "cap" else v[key].float() for v in d.values()]
        s = sum(float(i.mean()) for i in ims) / len(ims)
        l = sum(float(lin(i).mean()) for i in ims) / len(ims)
        y = sum(float((lin(i)[0] * torch.tensor([0.2126, 0.7152, 0.0722])[:, None, None]).sum(0).mean()) for i in ims) / len(ims)
        row[key] = f"{s:.3f}/{enc(l):.3f}/{enc(y):.3f}"
    print(scene, row, flush=True)
