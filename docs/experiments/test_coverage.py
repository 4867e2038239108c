"""How far each test view is from the training views (docs/real-scenes.md, "Sofa: 3D under its 2D target"):
per test view, PSNR / SSIM of the render against the normal-light photo and the share of its pixels that few
training views see. Each pixel is back-projected with the rendered depth (OpenCV camera, depth along the
optical axis) and counted in every training camera whose image it falls into. From the repository root:
    .venv/bin/python docs/experiments/test_coverage.py outputs/bench/lom-holdout/runs/sofa/naka-gs/naka-gs/config.yml
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
train_view = viewmat_from_c2w(train.camera_to_worlds.float())
train_k = train.get_intrinsics_matrices().float()


def seen_by(points: torch.Tensor) -> torch.Tensor:
    """For world points [N, 3], how many training images each falls into (in front of the camera)."""
    count = torch.zeros(len(points))
    for t in range(len(train)):
        cam = points @ train_view[t, :3, :3].T + train_view[t, :3, 3]
        uv = cam[:, :2] / cam[:, 2:].clamp_min(1e-6) @ train_k[t, :2, :2].T + train_k[t, :2, 2]
        w, h = float(train.width[t]), float(train.height[t])
        count += ((cam[:, 2] > 0.01) & (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h)).float()
    return count


names = [Path(f).name for f in datamanager.eval_dataset.image_filenames]
for i in range(len(cameras)):
    camera = cameras[i : i + 1]
    out = model.get_outputs_for_camera(camera.to(model.device))
    render, depth = out["rgb"].clamp(0, 1).cpu(), out["depth"][..., 0].cpu()
    truth = truths[i]["image"][..., :3]
    truth = truth.float() / 255 if truth.dtype == torch.uint8 else truth.float()
    ssim = float(ssim_fn(render.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], data_range=1.0))
    k = camera.get_intrinsics_matrices()[0].float()
    v, u = torch.meshgrid(torch.arange(depth.shape[0]) + 0.5, torch.arange(depth.shape[1]) + 0.5, indexing="ij")
    points = torch.stack([(u - k[0, 2]) / k[0, 0] * depth, (v - k[1, 2]) / k[1, 1] * depth, depth], -1).reshape(-1, 3)
    view = viewmat_from_c2w(camera.camera_to_worlds.float())[0]
    count = seen_by((points - view[:3, 3]) @ view[:3, :3])
    print(
        f"{names[i]}: {psnr(render, truth):.2f} dB / {ssim:.3f}; pixels seen by 0 / <= 2 / <= 5 training views: "
        f"{(count == 0).float().mean():.3f} / {(count <= 2).float().mean():.3f} / {(count <= 5).float().mean():.3f}"
    )
