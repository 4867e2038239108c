"""Culling the Gaussians no training view sees (docs/real-scenes.md, lever "Culling Gaussians that no training
view sees"): after training, zero the opacity of every Gaussian whose centre falls into no training image
and score the test views against their normal-light photos, before and after. From the repository root:
    .venv/bin/python docs/experiments/cull_unseen.py outputs/bench/lom-holdout/runs/sofa/naka-gs/naka-gs/config.yml
"""

import sys
from pathlib import Path

import torch
from torchmetrics.functional import structural_similarity_index_measure as ssim_fn
from training_views import load_run, seen_by

from naka_gs_plugin.metrics import psnr

torch.set_grad_enabled(False)
model, cameras, truths, _, train = load_run(Path(sys.argv[1]))
seen = seen_by(model.means.detach(), train) > 0


def scores() -> str:
    rows = []
    for i, truth in enumerate(truths):
        render = model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))["rgb"].clamp(0, 1).cpu()
        ssim = float(ssim_fn(render.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], data_range=1.0))
        rows.append((psnr(render, truth), ssim))
    mean = torch.tensor(rows).mean(0)
    return f"{mean[0]:.2f} dB / {mean[1]:.4f} (views: {', '.join(f'{p:.2f}' for p, _ in rows)})"


print(f"all {len(seen)} Gaussians: {scores()}")
model.gauss_params["opacities"].data[~seen] = -30.0  # sigmoid(-30) ~ 1e-13: invisible
print(f"without the {int((~seen).sum())} no training view sees: {scores()}")
