"""BlueHawaii by eye: test views' normal-light truth (left) beside a trained run's renders (right), half size.
    .venv/bin/python docs/experiments/realx3d_colour/truth_vs_render.py \\
        outputs/bench/bluehawaii-floor/runs/BlueHawaii/naka-gs/tone-capture/config.yml docs/img/bluehawaii_truth_vs_render.jpg
Views: the indices of the test split to show (default 0 2 4: views 1, 3 and 5); each row is scored as ns-eval scores it.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from nerfstudio.utils.eval_utils import eval_setup

torch.set_grad_enabled(False)
config, out = Path(sys.argv[1]), Path(sys.argv[2])
views = [int(v) for v in sys.argv[3:]] or [0, 2, 4]
_, pipeline, _, step = eval_setup(config, test_mode="test")
pipeline.eval()
rows = []
for index, (camera, batch) in enumerate(pipeline.datamanager.fixed_indices_eval_dataloader):
    if index not in views:
        continue
    outputs = pipeline.model.get_outputs_for_camera(camera)
    metrics = pipeline.model.get_image_metrics_and_images(outputs, batch)[0]
    truth = batch["image"][..., :3].float()
    truth = truth / 255.0 if batch["image"].dtype == torch.uint8 else truth
    pair = np.concatenate([truth.cpu().numpy(), outputs["rgb"].clamp(0, 1).cpu().numpy()], axis=1)
    h, w = pair.shape[:2]
    rows.append(cv2.resize(pair, (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    print(f"test view {index}: PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.3f}, LPIPS {metrics['lpips']:.3f}")
image = (np.concatenate(rows, axis=0) * 255.0 + 0.5).astype(np.uint8)
cv2.imwrite(str(out), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
print(f"step {step}: wrote {out}")
