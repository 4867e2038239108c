"""Where a trained LOM run loses SSIM (docs/real-scenes.md, "Exposure as a linear-light gain"): renders its
test views and scores them against the normal-light photos as they are, after a per-channel affine fit to
the photo (the tone upper bound), against a blurred photo (softness) and blurred (noise); plus contrast
(s.d. of the grey image). Saves render and truth per view to OUT. From the repository root:
    .venv/bin/python docs/experiments/tone/ssim_diag.py outputs/bench/lom-holdout/runs/bike/naka-gs/naka-gs/config.yml /tmp/diag/bike
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch
from nerfstudio.utils.eval_utils import eval_setup
from torchmetrics.functional import structural_similarity_index_measure as ssim_fn

cfg = Path(sys.argv[1])
out = Path(sys.argv[2])
out.mkdir(parents=True, exist_ok=True)
_, pipeline, _, _ = eval_setup(cfg, test_mode="test")
dm = pipeline.datamanager
model = pipeline.model
res = []
for i, (camera, batch) in enumerate(dm.fixed_indices_eval_dataloader):
    with torch.no_grad():
        outs = model.get_outputs_for_camera(camera)
    r = outs["rgb"].clamp(0, 1).cpu()
    gt = batch["image"][..., :3].cpu().float()
    torch.save({"render": r, "gt": gt}, out / f"view{i}.pt")

    def S(a, b):
        return float(ssim_fn(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], data_range=1.0))

    def P(a, b):
        return float(-10 * torch.log10(((a - b) ** 2).mean()))

    # per-channel affine fit of render to truth
    fit = torch.empty_like(r)
    for c in range(3):
        x = r[..., c].reshape(-1)
        y = gt[..., c].reshape(-1)
        X = torch.stack([x, torch.ones_like(x)], 1)
        sol = torch.linalg.lstsq(X, y[:, None]).solution
        fit[..., c] = (X @ sol).reshape(r.shape[:2])

    def blur(im, s):
        k = int(3 * s) * 2 + 1
        import torchvision.transforms.functional as TF

        return TF.gaussian_blur(im.permute(2, 0, 1), [k, k], [s, s]).permute(1, 2, 0)

    row = dict(
        view=i,
        psnr=P(r, gt),
        ssim=S(r, gt),
        psnr_affine=P(fit.clamp(0, 1), gt),
        ssim_affine=S(fit.clamp(0, 1), gt),
        ssim_gt_blur1=S(r, blur(gt, 1.0)),
        ssim_both_blur1=S(blur(r, 1.0), blur(gt, 1.0)),
        ssim_r_blur07=S(blur(r, 0.7), gt),
        mean_r=r.mean((0, 1)).tolist(),
        mean_gt=gt.mean((0, 1)).tolist(),
        std_r=float(r.mean(-1).std()),
        std_gt=float(gt.mean(-1).std()),
    )
    res.append(row)
    print(json.dumps(row))
keys = [k for k in res[0] if k.startswith(("psnr", "ssim", "std"))]
print("MEAN", {k: round(float(np.mean([r[k] for r in res])), 4) for k in keys})
