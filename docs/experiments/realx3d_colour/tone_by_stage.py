"""Where BlueHawaii's enhanced shadows get lifted: linear brightness per stage, binned by the capture's level.

Every third training view at 882x586; each image blurred by 3 px in linear light; bins of the blurred capture's
mean 8-bit code. Columns: the capture, the Naka image, the network's output, the final training target (capture
chroma, the network's tone, the scene exposure) and the normal-light reference; last, the final target over the
reference per channel. Diagnosis only (docs/real-scenes.md).
    .venv/bin/python docs/experiments/realx3d_colour/tone_by_stage.py
"""

from pathlib import Path

import cv2
import kornia
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, read_split
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.enhance.stages import ExposureStage, to_float01

torch.set_grad_enabled(False)
SCENE = Path("../shared/data/realx3d/BlueHawaii")
STAGES = ["capture", "naka", "network", "final", "reference"]


def blurred_linear(image):
    linear = kornia.color.rgb_to_linear_rgb(image.permute(2, 0, 1).clamp(0, 1))[None]
    return kornia.filters.gaussian_blur2d(linear, (9, 9), (3, 3))[0].reshape(3, -1)


enhance = EnhanceConfig(exposure="none", tone="network")
dm = LowLightDatamanagerConfig(dataparser=LowLightDataParserConfig(data=SCENE), enhance=enhance).setup(device="cpu")
lows = [to_float01(d["image"]) for d in dm.load_unenhanced_train()]
final = ExposureStage().apply_all(dm.enhancer.enhance_images(lows))
naka, correction = dm.enhancer.view_stages[:2]
naka.prepare(lows)
names = [p.name for p in read_split(SCENE, "transforms_train.json").images]
references = {p.stem: p for p in read_split(SCENE, "transforms_reference.json").images}
rows = {k: [] for k in STAGES + ["code"]}
for i in range(0, len(lows), 3):
    low = lows[i]
    h, w = low.shape[:2]
    reference = to_float01(
        torch.from_numpy(cv2.resize(read_rgb(references[Path(names[i]).stem]), (w, h), interpolation=cv2.INTER_AREA))
    )
    naka_image = naka.apply(low, low)
    images = [low, naka_image, correction.apply(naka_image, low), final[i], reference]
    for k, image in zip(STAGES, images):
        rows[k].append(blurred_linear(image))
    code = kornia.filters.gaussian_blur2d((low * 255).permute(2, 0, 1)[None], (9, 9), (3, 3))[0].mean(0)
    rows["code"].append(code.reshape(-1))
code = torch.cat(rows["code"])
edges = [0, 0.25, 0.5, 1, 2, 4, 8, 16, 32, 256]
print("capture code | share | mean linear brightness per stage | final / reference (r, g, b)")
for a, b in zip(edges[:-1], edges[1:]):
    sel = (code >= a) & (code < b)
    means = {k: torch.cat(rows[k], 1)[:, sel].mean(1) for k in STAGES}
    cells = " | ".join(f"{k} {float(v.mean()):.4f}" for k, v in means.items())
    ratio = (means["final"] / means["reference"]).tolist()
    print(f"[{a}, {b}) | {float(sel.float().mean()) * 100:.1f} % | {cells} | {', '.join(f'{r:.2f}' for r in ratio)}")
