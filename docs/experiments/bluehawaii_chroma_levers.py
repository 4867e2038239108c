"""2D colour levers on RealX3D BlueHawaii (the validation scene), scored against its references.

Reads the default enhancement's cached per-view output (Naka + shipped network + capture chroma, before
the exposure step), re-takes the chromaticity from the dark capture with a per-channel black level
removed (the p-th percentile of each channel's blurred linear values over the scene), keeps each pixel's
linear brightness, applies the default exposure step and scores like `naka-gs-enhance --reference`:

    .venv/bin/naka-gs-enhance ../shared/data/realx3d/BlueHawaii --out outputs/bluehawaii-2d-default  # fills the cache
    .venv/bin/python docs/experiments/bluehawaii_chroma_levers.py
"""

from pathlib import Path

import kornia
import torch

from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, read_split
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.enhance.stages import ExposureStage, to_float01
from naka_gs_plugin.scripts.enhance import score_against

SCENE = Path("../shared/data/realx3d/BlueHawaii")
dm = LowLightDatamanagerConfig(
    dataparser=LowLightDataParserConfig(data=SCENE), enhance=EnhanceConfig(exposure="none")
).setup(device="cpu")
lows = [to_float01(d["image"]) for d in dm.load_unenhanced_train()]
cached = dm.enhancer.enhance_images(lows)  # warm cache: the default output before the exposure step
names = [p.name for p in read_split(SCENE, "transforms_train.json").images]
by_stem = {p.stem: p for p in read_split(SCENE, "transforms_reference.json").images}
refs = [by_stem[Path(n).stem] for n in names]


def blurred_linear(low):
    x = kornia.filters.gaussian_blur2d(low.permute(2, 0, 1)[None], (9, 9), (3.0, 3.0), border_type="replicate")
    return kornia.color.rgb_to_linear_rgb(x.clamp(0, 1))[0]  # [3, H, W]


captures = [blurred_linear(low) for low in lows]
for p in (None, 0.1, 1.0, 5.0):
    if p is None:
        black = torch.zeros(3, 1, 1)
    else:
        sample = torch.cat([c.reshape(3, -1)[:, ::7] for c in captures], 1)
        black = torch.quantile(sample, p / 100, dim=1)[:, None, None]
    out = []
    for img, cap in zip(cached, captures):
        lin = kornia.color.rgb_to_linear_rgb(img.permute(2, 0, 1).clamp(0, 1))
        c = (cap - black).clamp(min=0) + 1e-4
        chroma = c / c.mean(0, keepdim=True)
        new = (lin.mean(0, keepdim=True) * chroma).clamp(0, 1)
        out.append(kornia.color.linear_rgb_to_rgb(new).permute(1, 2, 0))
    out = ExposureStage().apply_all(out)
    print(f"black level percentile {p}: {[round(float(b), 5) for b in black.flatten()]}")
    score_against(out, refs, names)
