"""2D record for the LOM protocol (docs/real-scenes.md, "2D ... + exposure"): a scene's hold-out weights on
its test views, low -> Naka -> network -> capture chroma (the default enhancement), with and without the
scene's exposure curve, and the network's own colour for comparison. The curve's parameter is the one the
scene's 3D run logged ("exposure lifted to 0.505 (luminance metering, gain K)" in its log.txt; ``gamma G``
for the power curve), so the last row scores exactly the images the 3D model trains towards. Images sRGB in
[0, 1]. From the repository root:
    .venv/bin/python docs/experiments/holdout_2d_exposure.py shrub 1.102 gain
    .venv/bin/python docs/experiments/holdout_2d_exposure.py shrub 0.925 power
"""

import json
import sys
from pathlib import Path

import kornia
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.checkpoint import load_correction
from naka_gs_plugin.enhance.correction import CorrectionRunner
from naka_gs_plugin.enhance.exposure import apply_curve
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.metrics import psnr

torch.set_grad_enabled(False)
scene, value, curve = sys.argv[1], float(sys.argv[2]), sys.argv[3]
root = Path("../shared/data/lom") / scene
runner = CorrectionRunner(load_correction(f"outputs/correction-loo/{scene}/best.pt"), "auto")
rows = {"network": [], "network + capture chroma": [], f"network + capture chroma + exposure ({curve} {value:.3f})": []}
for frame in json.loads((root / "transforms_test.json").read_text())["frames"]:
    name = Path(frame["file_path"]).name
    low = torch.from_numpy(read_rgb(root / "low" / name))
    naka = naka_enhance(low, 0.05)
    enhanced = runner(low.permute(2, 0, 1)[None], naka.permute(2, 0, 1)[None])["enhanced"][0].permute(1, 2, 0)
    truth = torch.from_numpy(read_rgb(root / "high" / name))
    chroma = capture_chroma(enhanced, low)
    for key, image in zip(rows, (enhanced.clamp(0, 1), chroma, apply_curve([chroma], curve, value)[0])):
        ssim = kornia.metrics.ssim(image.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], 11).mean()
        rows[key].append((psnr(image, truth), float(ssim)))
for key, scores in rows.items():
    n = len(scores)
    print(
        f"{scene} {key}: PSNR {sum(p for p, _ in scores) / n:.2f} SSIM {sum(s for _, s in scores) / n:.3f} ({n} views)"
    )
