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
from scene_2d import score_variants  # noqa: E402

torch.set_grad_enabled(False)


def variant_views(scene, lows, base, variant):
    sigma, codes = (float(v) for v in variant.split(":"))
    return f"wide chroma {sigma:g} px below {codes:g} codes", [
        with_chroma(i, wide_chroma(lo, sigma, codes)) for i, lo in zip(base, lows)
    ]


score_variants(["BlueHawaii", "chair"], ["48:4"], variant_views)
