"""RealX3D: every 5th training view at 1/4 size, enhanced with the defaults up to capture chroma; the
scene's sRGB mean and its metered level (sRGB of the mean linear luminance), and the exposure exponent
each metering rule picks. Caches the enhanced views in /tmp/exp/realx3d.pt."""

import json
from pathlib import Path

import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.exposure import METERED_TARGET, MIDDLE_GREY, apply_gamma, lift_gamma
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer

torch.set_grad_enabled(False)
D = Path(__file__).resolve().parents[4] / "shared" / "data" / "realx3d"
CACHE = Path("/tmp/exp/realx3d.pt")
W = torch.tensor([0.2126, 0.7152, 0.0722])


def quarter(path):
    im = torch.from_numpy(read_rgb(path)).permute(2, 0, 1)[None]
    return torch.nn.functional.interpolate(im, scale_factor=0.25, mode="area")[0].permute(1, 2, 0).contiguous()


if CACHE.exists():
    scenes = torch.load(CACHE)
else:
    enh = Enhancer(EnhanceConfig(exposure="none", use_cache=False))
    scenes = {}
    for tj in sorted(D.glob("*/transforms_train.json")):
        frames = json.load(open(tj))["frames"][::5]
        low = [quarter(tj.parent / f["file_path"]) for f in frames]
        scenes[tj.parent.name] = [im.half() for im in enh.enhance_images(low, description=tj.parent.name)]
    torch.save(scenes, CACHE)


def lin(x):
    x = x.float().clamp(0, 1)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def enc(v):
    return 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055


for name, ims in scenes.items():
    s = sum(float(i.float().mean()) for i in ims) / len(ims)
    y = sum(float((lin(i) * W).sum(-1).mean()) for i in ims) / len(ims)
    clip = sum(float((i.float().amax(-1) > 0.98).float().mean()) for i in ims) / len(ims)
    ims = [i.float() for i in ims]
    rules = {"mean 0.461": lift_gamma(ims, MIDDLE_GREY, "mean"), "luminance 0.505": lift_gamma(ims, METERED_TARGET)}
    after = "  ".join(
        f"{k}: g {g:.3f} -> mean {sum(float(i.mean()) for i in apply_gamma(ims, g)) / len(ims):.3f}" for k, g in rules.items()
    )
    print(f"{name:11s} sRGB mean {s:.3f} metered {enc(y):.3f} clipped {clip:.2%} | {after}", flush=True)
