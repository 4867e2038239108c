"""2D probe of wide chroma (``levers_2d.py wide:S:T``) on BlueHawaii and on LOM scenes: below ``T`` codes of the
filtered capture, the chromaticity of the capture low-passed over ``S`` px in linear light (a shadow takes the
colour of the lit surfaces around it) instead of its own. Each variant keeps the default enhancement's brightness
(Naka, network, capture tone), then goes through the scene's exposure step and is scored against the normal-light
photos (``naka-gs-enhance``'s scoring). BlueHawaii: its 30 training views against their references, shipped
weights; a LOM scene: its training views against their photos, hold-out weights ``outputs/correction-loo/SCENE/best.pt``.
    .venv/bin/python docs/experiments/realx3d_colour/wide_chroma_2d.py BlueHawaii chair -- 48:4 48:8
"""

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1]))
from levers_2d import wide_chroma, with_chroma  # noqa: E402
from scene_2d import scene_views  # noqa: E402

from naka_gs_plugin.enhance.stages import ExposureStage  # noqa: E402
from naka_gs_plugin.scripts.enhance import score_against  # noqa: E402

torch.set_grad_enabled(False)
args = sys.argv[1:]
scenes, variants = (args[: args.index("--")], args[args.index("--") + 1 :]) if "--" in args else (args, ["48:4"])
for scene in scenes or ["BlueHawaii", "chair"]:
    lows, base, refs, names = scene_views(scene)
    print(f"{scene}, default:", flush=True)
    score_against(ExposureStage().apply_all(base), refs, names)
    for variant in variants:
        sigma, codes = (float(v) for v in variant.split(":"))
        out = [with_chroma(i, wide_chroma(lo, sigma, codes)) for i, lo in zip(base, lows)]
        print(f"{scene}, wide chroma {sigma:g} px below {codes:g} codes:", flush=True)
        score_against(ExposureStage().apply_all(out), refs, names)
