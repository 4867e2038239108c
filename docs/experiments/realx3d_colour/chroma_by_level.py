"""JPEG chroma against luma in the dark captures of all eight RealX3D scenes (no references needed).

Every third training view, blurred 3 px, area-downscaled to 220x146; per bin of the capture's luma Y (8-bit
codes) the mean Cr / Y and Cb / Y. A loss of chroma that the camera makes in its darkest codes would show in
every scene as a ratio rising with Y; scene content moves these ratios too.

    .venv/bin/python docs/experiments/realx3d_colour/chroma_by_level.py
"""

from pathlib import Path

import cv2
import numpy as np

ROOT = Path("../shared/data/realx3d")
YCC = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
EDGES = np.array([0, 1.1, 2.6, 4, 6.8, 10.9, 16, 25, 40, 255])

print("Y bins (codes):", " ".join(f"{a:g}-{b:g}" for a, b in zip(EDGES[:-1], EDGES[1:])))
for scene in sorted(p for p in ROOT.iterdir() if p.is_dir()):
    ycc = []
    for path in sorted((scene / "train").glob("*.JPG"))[::3]:
        image = cv2.GaussianBlur(cv2.imread(str(path))[:, :, ::-1].astype(np.float32), (0, 0), 3)
        ycc.append(cv2.resize(image, (220, 146), interpolation=cv2.INTER_AREA).reshape(-1, 3) @ YCC.T)
    ycc = np.concatenate(ycc)
    for name, channel in (("Cr/Y", 2), ("Cb/Y", 1)):
        cells = []
        for a, b in zip(EDGES[:-1], EDGES[1:]):
            m = (ycc[:, 0] >= a) & (ycc[:, 0] < b)
            cells.append(f"{ycc[m, channel].mean() / ycc[m, 0].mean():6.3f}" if m.sum() > 50 else "     -")
        print(f"{scene.name if channel == 2 else '':11s} {name} {' '.join(cells)}")
