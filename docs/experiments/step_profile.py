"""Where a full-size CPU training step goes (issue 34's first profile; docs/cpu.md, "Where a full-size step goes").

Resumes a trained run (past step 6,000, so every step is at full size) for STEPS steps under cProfile,
in this process, with evaluation and saving out of the window, and prints the wall per step and the
functions with the most own time and the most cumulative time. With KEEP, the run's Gaussians are first
pruned to the KEEP most opaque ones (gsplat's ``remove``, optimizer and strategy state included), to see
the per-pixel cost that does not depend on the Gaussians. With DOWNSCALE (2 or 4; KEEP 0 keeps every
Gaussian), the steps train at that fraction of full size, as the resolution schedule's early phases do. With
``time`` last, no profiler: the median wall of a whole step (the trainer's loop, callbacks included, from one
step's start to the next's), then the median of the rasterizer's call alone, forward and backward, on the last
step's inputs (issue 34's "a full-size step against the rasterizer's forward+backward"), and their ratio. From
the repository root:

    .venv/bin/python docs/experiments/step_profile.py CONFIG [STEPS] [KEEP] [DOWNSCALE] [time]
        e.g. outputs/bench/lom-holdout/runs/bike/naka-gs/naka-gs/config.yml (a warm cache: no enhancement)
"""

import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path

import torch
import yaml
from gsplat.strategy.ops import remove


def rasterizer_alone(model, kwargs: dict, repeats: int = 30) -> float:
    """Median seconds of the model's rasterizer call, forward and backward, on copies of one step's inputs
    (leaves, so autograd runs only the rasterizer's backward; seeded random output gradients)."""
    gen = torch.Generator().manual_seed(0)
    leaf = lambda v: v.detach().clone().requires_grad_(True)  # noqa: E731
    inputs = {k: v if k in ("viewmats", "Ks") else leaf(v) for k, v in kwargs.items() if isinstance(v, torch.Tensor)}
    if isinstance(kwargs["colors"], tuple):  # splatfacto's (features_dc, features_rest), as the model passes them
        inputs["colors"] = tuple(leaf(v) for v in kwargs["colors"])
    rest = {k: v for k, v in kwargs.items() if k not in inputs}
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        render, alpha, _ = model._rasterize(inputs["means"].device, **inputs, **rest)
        if not times:
            grads = (torch.randn(render.shape, generator=gen), torch.randn(alpha.shape, generator=gen))
        torch.autograd.backward((render, alpha), grads)
        times.append(time.perf_counter() - start)
        for v in inputs.values():
            for t in v if isinstance(v, tuple) else (v,):
                t.grad = None
    return statistics.median(times[1:])


def main(config_path: Path, steps: int, keep: int | None, downscale: int, profiled: bool = True) -> None:
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
    if not profiled:
        starts, captured = [], {}
        train_iteration, rasterize = trainer.train_iteration, model._rasterize

        def timed_iteration(step):
            starts.append(time.perf_counter())
            return train_iteration(step)

        def capturing(device, **kwargs):
            captured.update(kwargs)
            return rasterize(device, **kwargs)

        trainer.train_iteration, model._rasterize = timed_iteration, capturing
        trainer.train()
        trainer.train_iteration, model._rasterize = train_iteration, rasterize
        step_s = statistics.median(b - a for a, b in zip(starts[10:], starts[11:]))
        raster_s = rasterizer_alone(model, captured)
        print(
            f"{1000 * step_s:.2f} ms per step (median over steps 10-{steps}), the rasterizer's call alone "
            f"{1000 * raster_s:.2f} ms forward+backward: {step_s / raster_s:.2f}x ({model.num_points} Gaussians, "
            f"{torch.get_num_threads()} threads, 1/{downscale} size, {captured['width']}x{captured['height']})"
        )
        return
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
        profiled=not (len(sys.argv) > 5 and sys.argv[5] == "time"),
    )
