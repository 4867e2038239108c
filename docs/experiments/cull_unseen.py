"""Culling the Gaussians no training view sees (docs/real-scenes.md, lever "Culling Gaussians that no training
view sees"): after training, zero the opacity of every Gaussian whose centre falls into no training image
and score the test views against their normal-light photos, before and after. From the repository root:
    .venv/bin/python docs/experiments/cull_unseen.py outputs/bench/lom-holdout/runs/sofa/naka-gs/naka-gs/config.yml
"""

import sys
from pathlib import Path

import torch
from nerfstudio.utils.eval_utils import eval_setup
from torchmetrics.functional import structural_similarity_index_measure as ssim_fn

from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.model.naka_gs_model import viewmat_from_c2w

torch.set_grad_enabled(False)
_, pipeline, _, _ = eval_setup(Path(sys.argv[1]), test_mode="test")
datamanager, model = pipeline.datamanager, pipeline.model
truths = datamanager.cached_eval  # undistorted; undistortion updates the cameras in place
datamanager.cached_train
cameras, train = datamanager.eval_dataset.cameras, datamanager.train_dataset.cameras
views = viewmat_from_c2w(train.camera_to_worlds.float())
ks = train.get_intrinsics_matrices().float()
means = model.means.detach()
seen = torch.zeros(len(means), dtype=torch.bool)
for t in range(len(train)):
    cam = means @ views[t, :3, :3].T + views[t, :3, 3]
    uv = cam[:, :2] / cam[:, 2:].clamp_min(1e-6) @ ks[t, :2, :2].T + ks[t, :2, 2]
    w, h = float(train.width[t]), float(train.height[t])
    seen |= (cam[:, 2] > 0.01) & (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h)


def scores() -> str:
    rows = []
    for i in range(len(cameras)):
        render = model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))["rgb"].clamp(0, 1).cpu()
        truth = truths[i]["image"][..., :3]
        truth = truth.float() / 255 if truth.dtype == torch.uint8 else truth.float()
        ssim = float(ssim_fn(render.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], data_range=1.0))
        rows.append((psnr(render, truth), ssim))
    mean = torch.tensor(rows).mean(0)
    return f"{mean[0]:.2f} dB / {mean[1]:.4f} (views: {', '.join(f'{p:.2f}' for p, _ in rows)})"


print(f"all {len(means)} Gaussians: {scores()}")
model.gauss_params["opacities"].data[~seen] = -30.0  # sigmoid(-30) ~ 1e-13: invisible
print(f"without the {int((~seen).sum())} no training view sees: {scores()}")
