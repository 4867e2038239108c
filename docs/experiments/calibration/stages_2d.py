"""BlueHawaii's 30 dark training views through the enhancement chain, stage by stage, with their references.

Writes ``outputs/calibration/bluehawaii_stages.pt``: per view the capture (882x586, as training loads it), the
Naka output, + the shipped network, + capture chroma, + capture tone (the default chain before the exposure step),
and the normal-light reference area-downscaled to that size. ``profile_2d.py`` fits profiles on these.

    .venv/bin/python docs/experiments/calibration/stages_2d.py [SCENE]
"""

import sys
from pathlib import Path

import cv2
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, read_split
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.enhance.stages import to_float01

torch.set_grad_enabled(False)
scene = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/realx3d/BlueHawaii")
ref_json = "transforms_reference.json" if (scene / "transforms_reference.json").exists() else None
dm = LowLightDatamanagerConfig(
    dataparser=LowLightDataParserConfig(data=scene), enhance=EnhanceConfig(exposure="none")
).setup(device="cpu")
lows = [to_float01(d["image"]) for d in dm.load_unenhanced_train()]
names = [p.name for p in read_split(scene, "transforms_train.json").images]
if ref_json:
    refs_paths = {p.stem: p for p in read_split(scene, ref_json).images}
    refs_paths = [refs_paths[Path(n).stem] for n in names]
else:  # LOM: high/ beside low/
    refs_paths = [scene / "high" / n for n in names]
enh = dm.enhancer
enh.view_stages[0].prepare(lows)
enh.view_stages[1].prepare(lows)
out = {"names": names, "low": [], "naka": [], "net": [], "chroma": [], "tone": [], "ref": []}
for low, rp in zip(lows, refs_paths):
    x = low
    for stage, key in zip(enh.view_stages, ("naka", "net", "chroma", "tone")):
        x = stage.apply(x, low)
        out[key].append(x.half())
    ref = read_rgb(rp)
    h, w = low.shape[:2]
    if ref.shape[:2] != (h, w):
        ref = cv2.resize(ref, (w, h), interpolation=cv2.INTER_AREA)
    out["ref"].append(torch.from_numpy(ref).half())
    out["low"].append(low.half())
    print(rp.name, flush=True)
dst = Path("outputs/calibration") / f"{scene.name.lower()}_stages.pt"
dst.parent.mkdir(parents=True, exist_ok=True)
torch.save(out, dst)
print(dst)
