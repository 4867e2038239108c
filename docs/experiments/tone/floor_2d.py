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

sys.path.insert(0, str(Path(__file__).parents[1]))
from scene_2d import scene_views  # noqa: E402

from naka_gs_plugin.enhance.stages import ExposureStage  # noqa: E402
from naka_gs_plugin.enhance.tone import capture_tone  # noqa: E402
from naka_gs_plugin.scripts.enhance import score_against  # noqa: E402

torch.set_grad_enabled(False)
VARIANTS = {"network": None, "capture, ceiling everywhere": {"floor": None}, "capture (ceiling below 2-4 codes)": {}}
for scene in sys.argv[1:] or ["BlueHawaii", "chair"]:
    lows, base, refs, names = scene_views(scene, tone="network")
    for name, options in VARIANTS.items():
        out = base if options is None else [capture_tone(i, lo, **options) for i, lo in zip(base, lows)]
        print(f"{scene}, tone {name}:", flush=True)
        score_against(ExposureStage().apply_all(out), refs, names)
