"""2D probe of capture tone restricted to the capture's floor (``tone capture`` now): the ceiling only where the
filtered capture is under 2 codes (below the range the view's gain is metered on: there the capture recorded no
signal and any lift is the network's), faded out by 4 codes; against ``tone network`` and the ceiling everywhere
(the first measured ``tone capture``). Each variant then through the scene's exposure step, scored against the normal-light photos (``naka-gs-enhance``'s scoring).
BlueHawaii: its 30 training views against their references, shipped weights; a LOM scene: its training views
against their photos, hold-out weights ``outputs/correction-loo/SCENE/best.pt``.
    .venv/bin/python docs/experiments/tone/floor_2d.py BlueHawaii chair
"""

import sys
from pathlib import Path

import torch

from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, read_split
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.enhance.stages import ExposureStage, to_float01
from naka_gs_plugin.enhance.tone import capture_tone
from naka_gs_plugin.scripts.enhance import score_against

torch.set_grad_enabled(False)
VARIANTS = {"network": None, "capture, ceiling everywhere": {"floor": None}, "capture (ceiling below 2-4 codes)": {}}
for scene in sys.argv[1:] or ["BlueHawaii", "chair"]:
    realx3d = scene == "BlueHawaii"
    root = Path("../shared/data/realx3d" if realx3d else "../shared/data/lom") / scene
    correction = "default" if realx3d else f"outputs/correction-loo/{scene}/best.pt"
    dm = LowLightDatamanagerConfig(
        dataparser=LowLightDataParserConfig(data=root),
        enhance=EnhanceConfig(correction=correction, tone="network", exposure="none"),
    ).setup(device="cpu")
    lows = [to_float01(d["image"]) for d in dm.load_unenhanced_train()]  # at the training resolution
    base = dm.enhancer.enhance_images(lows)
    names = [p.name for p in read_split(root, "transforms_train.json").images]
    if realx3d:
        by_stem = {p.stem: p for p in read_split(root, "transforms_reference.json").images}
        refs = [by_stem[Path(n).stem] for n in names]
    else:
        refs = [root / "high" / n for n in names]
    for name, options in VARIANTS.items():
        out = base if options is None else [capture_tone(i, lo, **options) for i, lo in zip(base, lows)]
        print(f"{scene}, tone {name}:", flush=True)
        score_against(ExposureStage().apply_all(out), refs, names)
