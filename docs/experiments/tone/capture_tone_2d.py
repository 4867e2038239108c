"""2D probe of capture tone (docs/real-scenes.md): the default enhancement of a LOM scene's training views with
``tone network`` and ``tone capture``, each through the scene's exposure step, scored against the views'
normal-light photos (PSNR, SSIM, LPIPS, colour error: ``naka-gs-enhance``'s scoring). Hold-out weights,
``outputs/correction-loo/SCENE/best.pt``. RealX3D BlueHawaii has its own references:
``naka-gs-enhance ../shared/data/realx3d/BlueHawaii --out DIR [--enhance.tone network]``.
    .venv/bin/python docs/experiments/tone/capture_tone_2d.py bike sofa
"""

import json
import sys
from pathlib import Path

import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.scripts.enhance import score_against

torch.set_grad_enabled(False)
for scene in sys.argv[1:] or ["bike", "chair", "shrub", "sofa"]:
    root = Path("../shared/data/lom") / scene
    names = [Path(f["file_path"]).name for f in json.loads((root / "transforms_train.json").read_text())["frames"]]
    lows = [torch.from_numpy(read_rgb(root / "low" / n)) for n in names]
    for tone in ("network", "capture"):
        enhancer = EnhanceConfig(correction=f"outputs/correction-loo/{scene}/best.pt", tone=tone).setup()
        print(f"{scene}, tone {tone}:", flush=True)
        score_against(enhancer.enhance_images(lows), [root / "high" / n for n in names], names)
