"""An independent LPIPS of ns-eval's saved renders: torchmetrics' own LPIPS module (its linear layers,
its arithmetic) with the AlexNet backbone naka-gs ships, on the 8-bit PNGs `ns-eval --render-output-path`
writes (each `eval_img_*.png` is ground truth | render side by side).

    .venv/bin/python docs/experiments/lpips_independent.py outputs/sofa-eval-renders outputs/sofa-eval.json
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torchmetrics.functional.image.lpips import _NoTrainLpips

from naka_gs_plugin.model.lpips import CONVS, SHIPPED

renders, eval_json = Path(sys.argv[1]), Path(sys.argv[2])
net = _NoTrainLpips(net="alex", pnet_rand=True)
ours = torch.load(SHIPPED, map_location="cpu", weights_only=True)
slices = dict(zip(CONVS, ("slice1", "slice2", "slice3", "slice4", "slice5")))
net.load_state_dict({f"net.{slices[i]}.{i}.{p}": ours[f"features.{i}.{p}"] for i in CONVS for p in ("weight", "bias")}, strict=False)
scores = []
for png in sorted(renders.glob("eval_img_*.png")):
    both = torch.from_numpy(np.asarray(Image.open(png).convert("RGB"), dtype=np.float32) / 255.0).permute(2, 0, 1)[None]
    w = both.shape[-1] // 2
    with torch.no_grad():
        scores.append(float(net(both[..., :w], both[..., w:], normalize=True)))
print(f"independent LPIPS over {len(scores)} views: {np.mean(scores):.4f} ({', '.join(f'{s:.4f}' for s in scores)})")
print(f"ns-eval's lpips: {json.loads(eval_json.read_text())['results']['lpips']:.4f}")
