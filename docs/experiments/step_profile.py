"""Where a full-size CPU training step goes (issue 34's first profile; docs/cpu.md, "Where a full-size step goes").

Resumes a trained run (past step 6,000, so every step is at full size) for STEPS steps under cProfile,
in this process, with evaluation and saving out of the window, and prints the wall per step and the
functions with the most own time and the most cumulative time. With KEEP, the run's Gaussians are first
pruned to the KEEP most opaque ones (gsplat's ``remove``, optimizer and strategy state included), to see
the per-pixel cost that does not depend on the Gaussians. With DOWNSCALE (2 or 4; KEEP 0 keeps every
Gaussian), the steps train at that fraction of full size, as the resolution schedule's early phases do. From the repository root:

    .venv/bin/python docs/experiments/step_profile.py CONFIG [STEPS] [KEEP] [DOWNSCALE]
        e.g. outputs/bench/lom-holdout/runs/bike/naka-gs/naka-gs/config.yml (a warm cache: no enhancement)
"""

import cProfile
import pstats
import sys
import time
from pathlib import Path

import torch
import yaml
from gsplat.strategy.ops import remove


def main(config_path: Path, steps: int, keep: int | None, downscale: int) -> None:
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    config.load_dir = config_path.parent / "nerfstudio_models"
    config.output_dir = Path("/tmp/naka-gs-step-profile")
    config.max_num_iterations = steps
    config.steps_per_save = config.steps_per_eval_image = config.steps_per_eval_all_images = 10**9
    config.steps_per_eval_batch = 10**9
    config.vis = "tensorboard"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="val")
    _ = trainer.pipeline.datamanager.cached_train
    model = trainer.pipeline.model
    model._get_downscale_factor = lambda: downscale if model.training else 1
    if keep and keep < model.num_points:
        opacity = model.gauss_params["opacities"].detach().squeeze(-1)
        drop = torch.ones_like(opacity, dtype=torch.bool)
        drop[torch.topk(opacity, keep).indices] = False
        optimizers = {name: trainer.optimizers.optimizers[name] for name in model.gauss_params}
        remove(model.gauss_params, optimizers, model.strategy_state, drop)
    profile = cProfile.Profile()
    start = time.perf_counter()
    profile.enable()
    trainer.train()
    profile.disable()
    wall = time.perf_counter() - start
    print(
        f"{1000 * wall / steps:.1f} ms per step over {steps} steps ({model.num_points} Gaussians, "
        f"{torch.get_num_threads()} threads, 1/{downscale} size)"
    )
    stats = pstats.Stats(profile)
    stats.sort_stats("tottime").print_stats(30)
    stats.sort_stats("cumulative").print_stats(60)


if __name__ == "__main__":
    main(
        Path(sys.argv[1]),
        int(sys.argv[2]) if len(sys.argv) > 2 else 50,
        int(sys.argv[3]) if len(sys.argv) > 3 else None,
        int(sys.argv[4]) if len(sys.argv) > 4 else 1,
    )
