"""Training step time after the enhancement ran in the same process (docs/cpu.md, "Training after the
correction ran in the same process"). Two measurements, from the repository root:

    NAKA_GS_CACHE=$(mktemp -d) .venv/bin/python docs/experiments/step_time.py resume CONFIG [STEPS]
        resumes a trained run (e.g. outputs/bench/lom-appearance/runs/shrub/naka-gs/affine/config.yml) for
        STEPS (100) more steps in this process and prints the wall time per step; an empty cache makes the
        enhancement run first, as in the bench; a warm one skips it.
    .venv/bin/python docs/experiments/step_time.py ssim WEIGHTS
        times the SSIM loss (pytorch_msssim, as splatfacto's) forward and backward on a 500x375 image,
        before and after one lean correction run with WEIGHTS (e.g. outputs/correction-loo/shrub/best.pt).
"""

import sys
import time
from pathlib import Path

import torch
import yaml
from pytorch_msssim import SSIM


def resume(config_path: Path, steps: int) -> None:
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    config.load_dir = config_path.parent / "nerfstudio_models"
    config.output_dir = Path("/tmp/naka-gs-step-time")
    config.max_num_iterations = steps  # nerfstudio counts these from the resumed step
    # nerfstudio saves and evaluates at steps divisible by these, counted from 0: none in the timed window.
    config.steps_per_save = config.steps_per_eval_image = config.steps_per_eval_all_images = 10**9
    config.steps_per_eval_batch = 10**9
    config.vis = "tensorboard"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="val")
    _ = trainer.pipeline.datamanager.cached_train  # loads and enhances the training images
    start = time.perf_counter()
    trainer.train()
    print(f"{1000 * (time.perf_counter() - start) / steps:.1f} ms per step over {steps} steps")


def ssim_time(weights: Path) -> None:
    from naka_gs_plugin.enhance.checkpoint import load_correction
    from naka_gs_plugin.enhance.correction import correct_image

    loss = SSIM(data_range=1.0, size_average=True, channel=3)
    render, target = torch.rand(1, 3, 375, 500, requires_grad=True), torch.rand(1, 3, 375, 500)

    def timed(label: str) -> None:
        for _ in range(3):
            (1 - loss(render, target)).backward()
        start = time.perf_counter()
        for _ in range(10):
            (1 - loss(render, target)).backward()
        print(f"{label}: SSIM forward + backward {100 * (time.perf_counter() - start):.1f} ms")

    timed("fresh process")
    with torch.no_grad():
        correct_image(load_correction(weights), torch.rand(375, 500, 3) * 0.1, torch.rand(375, 500, 3), mode="lean")
    timed("after one lean correction run")


if __name__ == "__main__":
    if sys.argv[1] == "resume":
        resume(Path(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 100)
    else:
        ssim_time(Path(sys.argv[2]))
