"""BlueHawaii's blue barrels in the dark captures: the capture's codes where the reference is blue.

Pixels whose reference is blue (b > r + 40 and b > g + 20, 8-bit codes) on training views 1, 10 and 20:
mean reference codes, mean dark-capture codes (raw and blurred 6 px), and the share of blue codes <= 1.

    .venv/bin/python docs/experiments/realx3d_colour/barrels.py
"""

from pathlib import Path

import cv2
import numpy as np

SCENE = Path("../shared/data/realx3d/BlueHawaii")
for i in (1, 10, 20):
    dark = cv2.imread(str(SCENE / f"train/{i:04d}.JPG"))[:, :, ::-1].astype(np.float32)
    ref = cv2.imread(str(SCENE / f"reference/{i:04d}.JPG"))[:, :, ::-1].astype(np.float32)
    ref = cv2.resize(ref, (dark.shape[1], dark.shape[0]), interpolation=cv2.INTER_AREA)
    blue = (ref[..., 2] > ref[..., 0] + 40) & (ref[..., 2] > ref[..., 1] + 20)
    blurred = cv2.GaussianBlur(dark, (0, 0), 6)
    print(
        f"view {i}: {blue.mean():.1%} of the pixels; reference {ref[blue].mean(0).round(1)}, capture "
        f"{dark[blue].mean(0).round(2)}, blurred {blurred[blue].mean(0).round(2)}, "
        f"blue codes <= 1: {(dark[blue][:, 2] <= 1).mean():.0%}"
    )
