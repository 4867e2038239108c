"""2D score of the default enhancement on the LOM protocol's test views, for one set of hold-out weights:
Naka -> network -> capture chroma -> the scene's exposure curve, the curve metered over the scene's
training views exactly as the datamanager does, so the rows score the images the 3D model would train
towards at the test poses. Images sRGB in [0, 1]; SSIM kornia's 11-px window (as ns-eval). From the root:
    .venv/bin/python docs/experiments/holdout_2d_pipeline.py 'outputs/correction-loo/{scene}/best.pt'
    .venv/bin/python docs/experiments/holdout_2d_pipeline.py 'outputs/correction-gpu/e25/correction-{scene}.pt'
"""

import json
import sys
from pathlib import Path

import kornia
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.exposure import apply_curve
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.metrics import psnr

torch.set_grad_enabled(False)
pattern = sys.argv[1]
scenes = sys.argv[2:] or ["bike", "chair", "shrub", "sofa"]
means = []
for scene in scenes:
    root = Path("../shared/data/lom") / scene
    views = {
        split: [
            Path(f["file_path"]).name for f in json.loads((root / f"transforms_{split}.json").read_text())["frames"]
        ]
        for split in ("train", "test")
    }
    config = EnhanceConfig(correction=pattern.format(scene=scene), use_cache=False)
    enhancer = config.setup()
    enhancer.enhance_images([torch.from_numpy(read_rgb(root / "low" / n)) for n in views["train"]], "train views")
    curve, value = enhancer.last_run["exposure_curve"], enhancer.last_run["exposure_value"]
    config.exposure = "none"
    test = enhancer.enhance_images([torch.from_numpy(read_rgb(root / "low" / n)) for n in views["test"]], "test views")
    scores = []
    for name, image in zip(views["test"], apply_curve(test, curve, value)):
        truth = torch.from_numpy(read_rgb(root / "high" / name))
        ssim = kornia.metrics.ssim(image.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], 11).mean()
        scores.append((psnr(image, truth), float(ssim), float(image.mean())))
    n = len(scores)
    row = [sum(s[i] for s in scores) / n for i in range(3)]
    means.append(row)
    print(
        f"{scene}: PSNR {row[0]:.2f} SSIM {row[1]:.4f} mean {row[2]:.3f} ({curve} {value:.3f}, {n} test views)",
        flush=True,
    )
print(f"mean: PSNR {sum(r[0] for r in means) / len(means):.2f} SSIM {sum(r[1] for r in means) / len(means):.4f}")
