"""How far each test view is from the training views (docs/real-scenes.md, "Sofa: 3D under its 2D target"):
per test view, PSNR / SSIM of the render against the normal-light photo and the share of its pixels that few
training views see. Each pixel is back-projected with the rendered depth (OpenCV camera, depth along the
optical axis) and counted in every training camera whose image it falls into. From the repository root:
    .venv/bin/python docs/experiments/test_coverage.py outputs/bench/lom-holdout/runs/sofa/naka-gs/naka-gs/config.yml
"""

import sys
from pathlib import Path

import torch
from torchmetrics.functional import structural_similarity_index_measure as ssim_fn
from training_views import load_run, seen_by

from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.model.naka_gs_model import viewmat_from_c2w

torch.set_grad_enabled(False)
model, cameras, truths, names, train = load_run(Path(sys.argv[1]))
for i, truth in enumerate(truths):
    camera = cameras[i : i + 1]
    out = model.get_outputs_for_camera(camera.to(model.device))
    render, depth = out["rgb"].clamp(0, 1).cpu(), out["depth"][..., 0].cpu()
    ssim = float(ssim_fn(render.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], data_range=1.0))
    k = camera.get_intrinsics_matrices()[0].float()
    v, u = torch.meshgrid(torch.arange(depth.shape[0]) + 0.5, torch.arange(depth.shape[1]) + 0.5, indexing="ij")
    points = torch.stack([(u - k[0, 2]) / k[0, 0] * depth, (v - k[1, 2]) / k[1, 1] * depth, depth], -1).reshape(-1, 3)
    view = viewmat_from_c2w(camera.camera_to_worlds.float())[0]
    count = seen_by((points - view[:3, 3]) @ view[:3, :3], train)
    print(
        f"{names[i]}: {psnr(render, truth):.2f} dB / {ssim:.3f}; pixels seen by 0 / <= 2 / <= 5 training views: "
        f"{(count == 0).float().mean():.3f} / {(count <= 2).float().mean():.3f} / {(count <= 5).float().mean():.3f}"
    )
