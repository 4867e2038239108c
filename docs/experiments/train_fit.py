"""How well a trained run fits its own training targets (docs/real-scenes.md, "Resolution schedule"): renders
every 3rd training view and scores it against the enhanced image it was trained towards (PSNR, SSIM) with
the 1 % luminance quantile of both (haze lifts the render's). From the repository root:
    .venv/bin/python docs/experiments/train_fit.py outputs/bench/lom-holdout/runs/sofa/naka-gs/naka-gs/config.yml
"""

import sys
from pathlib import Path

import torch
from nerfstudio.utils.eval_utils import eval_setup
from torchmetrics.functional import structural_similarity_index_measure as ssim_fn

from naka_gs_plugin.enhance.exposure import LUMA
from naka_gs_plugin.enhance.pipeline import to_float01
from naka_gs_plugin.metrics import psnr

_, pipeline, _, _ = eval_setup(Path(sys.argv[1]), test_mode="val")
datamanager, model = pipeline.datamanager, pipeline.model
targets = datamanager.cached_train  # enhanced and undistorted; undistortion updates the cameras in place
cameras = datamanager.train_dataset.cameras
luma = torch.tensor(LUMA)


def q01(image: torch.Tensor) -> float:
    return float(torch.quantile((image @ luma).flatten()[::5], 0.01))


scores = []
for i in range(0, len(cameras), 3):
    with torch.no_grad():
        render = model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))["rgb"].clamp(0, 1).cpu()
    target = to_float01(targets[i]["image"])  # uint8 or float32 cache (cache_images_type)
    ssim = float(ssim_fn(render.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], data_range=1.0))
    scores.append((psnr(render, target), ssim))
    print(
        f"view {i}: {scores[-1][0]:.2f} dB / {ssim:.3f}, 1% luminance render {q01(render):.3f} target {q01(target):.3f}"
    )
mean = torch.tensor(scores).mean(0)
print(f"training-view fit: {mean[0]:.2f} dB / {mean[1]:.3f} over {len(scores)} views")
