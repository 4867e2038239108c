"""The cpu-fast compositing stages on a real training step's inputs (docs/cpu.md, "Row spans before the kernels").

Resumes a trained run for one step, keeps the inputs of its first full-size compositing call (2D means,
conics, colours, opacities, depths, radii of every Gaussian), then times sort+bin, the forward and backward
kernels and the slot reduction on them (median of REPEATS renders, forward + backward of a fixed random
loss) and prints how many list slots, row-span pixels and composited pairs the render has. Run it in two
checkouts (e.g. a ``git worktree`` of the older commit) for an A/B; ``--save FILE`` keeps the outputs and
gradients so that the two can be compared bit for bit with ``--compare FILE``. From the repository root:

    .venv/bin/python docs/experiments/raster_kernels.py CONFIG [--repeats 5] [--save F | --compare F]
        e.g. outputs/bench/bluehawaii-ssim/runs/BlueHawaii/naka-gs/naka-gs/config.yml
"""

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import yaml

import naka_gs_plugin.model.rasterize_cpu_fast as rf


def capture_inputs(config_path: Path) -> list:
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    config.load_dir = config_path.parent / "nerfstudio_models"
    config.output_dir = Path("/tmp/naka-gs-raster-kernels")
    config.max_num_iterations = 1
    config.steps_per_save = config.steps_per_eval_image = config.steps_per_eval_all_images = 10**9
    config.steps_per_eval_batch = 10**9
    config.vis = "tensorboard"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="val")
    captured = []
    composite = rf._TileComposite.apply

    def keep(*args):
        if not captured and args[7] > 64:  # the warm-up's 8x8 render is not the step's
            captured.extend(a.detach().clone() if torch.is_tensor(a) else a for a in args)
        return composite(*args)

    rf._TileComposite.apply = keep
    try:
        trainer.train()
    finally:
        rf._TileComposite.apply = composite
    return captured


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--save", type=Path)
    parser.add_argument("--compare", type=Path)
    args = parser.parse_args()
    means2d, conics, opacities, colors, backgrounds, depths, radii, width, height, absgrad = capture_inputs(args.config)
    gen = torch.Generator().manual_seed(0)
    weights = torch.rand(1, height, width, colors.shape[-1] + 1, generator=gen)
    times = []
    for repeat in range(args.repeats + 1):
        inputs = [x.detach().clone().requires_grad_() for x in (means2d, conics, opacities, colors)]
        with rf.profile_stages() as stages:
            started = time.perf_counter()
            out, alpha = rf._TileComposite.apply(*inputs, backgrounds, depths, radii, width, height, absgrad)
            (torch.cat([out, alpha], -1) * weights).sum().backward()
            stages["total"] = time.perf_counter() - started
        if repeat:  # the first render pays page faults of fresh scratch memory
            times.append(dict(stages))
    print(f"{args.config}: {means2d.shape[1]} Gaussians, {width}x{height}, {rf.numba.get_num_threads()} threads")
    print(
        "ms (median of",
        args.repeats,
        "):",
        {k: round(1000 * statistics.median(t[k] for t in times), 1) for k in times[0]},
    )
    results = [out.detach(), alpha.detach(), *[x.grad for x in inputs], inputs[0].absgrad]
    if args.save:
        torch.save(results, args.save)
    if args.compare:
        other = torch.load(args.compare)
        same = [torch.equal(a, b) for a, b in zip(results, other)]
        print("bit for bit equal (colours, alphas, grads of means2d, conics, opacities, colours, absgrad):", same)
    # What the render holds: visible entries, list slots, box pixels vs row-span pixels, composited pairs.
    np_ = lambda x: x.detach().contiguous().numpy()  # noqa: E731
    consts = np.array([0.5, rf.ALPHA_MAX, rf.ALPHA_MIN, 0.0], dtype=np.float32)
    entries = rf._visible_by_depth(np_(radii), np_(opacities), np_(depths), consts[2])
    dim = colors.shape[-1]
    records, boxes = rf._make_records(
        entries, np_(means2d).reshape(-1, 2), np_(conics).reshape(-1, 3), np_(opacities).reshape(-1),
        np_(colors).reshape(-1, dim), radii.reshape(-1).float().numpy(), consts, width, height,
    )  # fmt: skip
    box_tiles = int(
        ((boxes[:, 1] // 16 - boxes[:, 0] // 16 + 1) * (boxes[:, 3] // 16 - boxes[:, 2] // 16 + 1))[
            boxes[:, 1] >= 0
        ].sum()
    )
    box_pixels = int(((boxes[:, 1] - boxes[:, 0] + 1) * (boxes[:, 3] - boxes[:, 2] + 1))[boxes[:, 1] >= 0].sum())
    if hasattr(rf, "_row_spans"):
        row_start, spans = rf._row_spans(records, boxes, np.arange(height, dtype=np.float32) + 0.5)
        span_pixels = int(np.maximum(spans[:, 1] - spans[:, 0] + 1, 0).sum())
        slots = int((rf._tile_pixels(boxes, row_start, spans)[1] > 0).sum())
        print(f"visible {len(entries)}, box tiles {box_tiles}, listed slots {slots}, box pixels {box_pixels}, "
              f"row-span pixels {span_pixels}")  # fmt: skip
    else:
        print(f"visible {len(entries)}, box tiles (all listed) {box_tiles}, box pixels {box_pixels}")


if __name__ == "__main__":
    main()
