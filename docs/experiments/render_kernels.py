"""Wall time per numba kernel of the cpu-fast renders of a trained run (docs/cpu.md, "ninth profile").

Loads the run with nerfstudio's ``eval_setup``, renders five of its training views at 1/SCALE of their size
(the resolution schedule's sizes: 4, 2, 1) through the model, forward and the backward of a random-weighted
sum of the image, and prints the milliseconds per render spent in each compiled kernel of the projection,
SH colours and compositing (a wrapper times every call), after one untimed pass. From the repository root:

    .venv/bin/python docs/experiments/render_kernels.py CONFIG [--scale 4] [--repeats 5]
"""

import argparse
import collections
import time
from pathlib import Path

import numba
import torch
from nerfstudio.utils.eval_utils import eval_setup

import naka_gs_plugin.model.project_cpu_fast as project_fast
import naka_gs_plugin.model.rasterize_cpu_fast as raster_fast


def time_kernels(seconds: dict) -> None:
    """Replace every numba kernel of the two modules by a wrapper that adds its wall seconds to ``seconds``."""
    for module in (raster_fast, project_fast):
        for name, kernel in list(vars(module).items()):
            if isinstance(kernel, numba.core.registry.CPUDispatcher):

                def timed(*args, _kernel=kernel, _name=name):
                    started = time.perf_counter()
                    result = _kernel(*args)
                    seconds[_name] += time.perf_counter() - started
                    return result

                setattr(module, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--scale", type=float, default=4.0)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    _, pipeline, _, _ = eval_setup(args.config, test_mode="val")
    model = pipeline.model
    model.eval()
    raster_fast.warm_up(torch.float32)  # before the wrappers: it reads the kernels' compile statistics
    seconds = collections.defaultdict(float)
    time_kernels(seconds)
    cameras = pipeline.datamanager.train_dataset.cameras
    views = list(range(0, len(cameras), max(1, len(cameras) // 4)))

    def render(view: int) -> None:
        camera = cameras[view : view + 1]
        camera.rescale_output_resolution(1.0 / args.scale)
        rgb = model.get_outputs(camera)["rgb"]
        (rgb * torch.randn(rgb.shape, generator=torch.Generator().manual_seed(view))).sum().backward()
        model.zero_grad(set_to_none=True)

    for view in views:
        render(view)
    seconds.clear()
    started = time.perf_counter()
    for _ in range(args.repeats):
        for view in views:
            render(view)
    renders = args.repeats * len(views)
    total = (time.perf_counter() - started) / renders
    print(f"{len(model.means)} Gaussians, 1/{args.scale:g} size: {total * 1e3:.1f} ms per render, forward + backward")
    for name, spent in sorted(seconds.items(), key=lambda item: -item[1]):
        print(f"{spent / renders * 1e3:8.2f} ms  {name}")
    print(f"{sum(seconds.values()) / renders * 1e3:8.2f} ms  in the kernels")


if __name__ == "__main__":
    main()
