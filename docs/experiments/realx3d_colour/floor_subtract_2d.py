"""2D probe of a black level estimated from the capture: per channel, a low percentile of the scene's captures
in linear light, each low-passed over ``S`` px (at 882 px of width; scaled with the view), subtracted in linear
light before the enhancement (Naka, network, capture chroma and tone all see the subtracted capture), then the
scene's exposure step; scored against the normal-light photos (``naka-gs-enhance``'s scoring). BlueHawaii: its 30
training views against their references, shipped weights; a LOM scene: hold-out weights
``outputs/correction-loo/SCENE/best.pt``. Variants ``Q:S`` or ``Q:S:C`` (percentile, sigma, at most C codes).

    .venv/bin/python docs/experiments/realx3d_colour/floor_subtract_2d.py BlueHawaii bike -- 1:48 0.1:48
"""

import sys
from pathlib import Path

import cv2
import kornia
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parents[1]))
from scene_2d import scene_views, score_variants  # noqa: E402

torch.set_grad_enabled(False)
CODE = 1.0 / (255 * 12.92)  # one 8-bit code of sRGB's linear toe, in linear light


def floor_subtracted(q: float, sigma: float, cap: float = float("inf")):
    def transform(lows):
        lin = [kornia.color.rgb_to_linear_rgb(lo.permute(2, 0, 1)).permute(1, 2, 0).numpy() for lo in lows]
        s = sigma * lows[0].shape[1] / 882
        wide = np.concatenate(
            [cv2.GaussianBlur(x, (0, 0), s, borderType=cv2.BORDER_REPLICATE).reshape(-1, 3) for x in lin]
        )
        floor = np.minimum(np.percentile(wide, q, axis=0), cap * CODE)
        print(
            f"  floor (percentile {q:g}, {s:.0f} px): r / g / b {np.round(floor / CODE, 3).tolist()} codes", flush=True
        )
        return [
            kornia.color.linear_rgb_to_rgb(torch.from_numpy(np.clip(x - floor, 0, None)).permute(2, 0, 1)).permute(
                1, 2, 0
            )
            for x in lin
        ]

    return transform


def variant_views(scene, lows, base, variant):
    q, sigma, *cap = (float(v) for v in variant.split(":"))
    _, out, _, _ = scene_views(scene, transform=floor_subtracted(q, sigma, *cap))
    return f"floor at percentile {q:g} over {sigma:g} px subtracted (at most {cap} codes)", out


score_variants(["BlueHawaii", "bike"], ["1:48"], variant_views)
