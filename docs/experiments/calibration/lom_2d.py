"""LOM leave-one-scene-out in 2D: a camera profile from three LOM scenes' pairs, used on the fourth's views.

For each scene X of bike, chair, shrub, sofa: ``naka-gs-calibrate`` on the other three scenes' low/high pairs (all
their views), the shipped network; then X's 40 dark views through the default chain, without and with that profile,
scored against X's normal-light photos (PSNR, SSIM, LPIPS, chroma L1). The shipped network was trained on LOL and
LOM: it already knows this camera.

    .venv/bin/python docs/experiments/calibration/lom_2d.py
"""

import tempfile
from pathlib import Path

import numpy as np
import torch

from naka_gs_plugin.data.pairs import find_pairs, load_pairs
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.scripts.calibrate import Calibrate
from naka_gs_plugin.scripts.enhance import score_against

LOM = Path("../shared/data/lom")
SCENES = ["bike", "chair", "shrub", "sofa"]
rows = []
for held in SCENES:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for sub in ("low", "high"):
            (root / sub).mkdir()
            for scene in SCENES:
                if scene != held:
                    for p in sorted((LOM / scene / sub).iterdir()):
                        (root / sub / f"{scene}_{p.name}").symlink_to(p.resolve())
        Calibrate(pairs=root, out=root / "lom.json", sheet_pairs=0).main()
        profile = Path(f"outputs/calibration/lom-without-{held}.json")
        profile.parent.mkdir(parents=True, exist_ok=True)
        profile.write_bytes((root / "lom.json").read_bytes())
    pairs = load_pairs(find_pairs(LOM / held))
    lows = [torch.from_numpy(p.low) for p in pairs]
    names = [p.name for p in pairs]
    for label, config in [("defaults", EnhanceConfig()), ("profile", EnhanceConfig(profile=profile))]:
        out = Enhancer(config).enhance_images(lows)
        with tempfile.TemporaryDirectory() as tmp:
            refs = []
            for p in pairs:
                path = Path(tmp) / f"{p.name}.png"
                import cv2

                cv2.imwrite(str(path), (p.high[..., ::-1] * 65535).round().astype(np.uint16))
                refs.append(path)
            m = score_against(out, refs, names)["means"]
        rows.append((held, label, m))
print("| held-out scene | chain | PSNR | SSIM | LPIPS | chroma L1 |")
print("|---|---|---|---|---|---|")
for held, label, m in rows:
    print(f"| {held} | {label} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m['lpips']:.3f} | {m['chroma_l1']:.3f} |")
for label in ("defaults", "profile"):
    ms = [m for _, lab, m in rows if lab == label]
    print(f"| mean | {label} | " + " | ".join(f"{np.mean([m[k] for m in ms]):.3f}" for k in ("psnr", "ssim", "lpips", "chroma_l1")) + " |")
