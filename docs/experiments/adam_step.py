"""Adam's step on a CPU for a splatfacto model's parameter groups: torch's default (a loop of whole-tensor ops per
parameter), ``foreach`` and ``fused`` (docs/cpu.md, "Around the rasterizer"). One Adam per group, as nerfstudio builds
them, each group one tensor of N Gaussians (means, DC, SH rest at degree 3, opacities, scales, quats). From the
repository root:

    .venv/bin/python docs/experiments/adam_step.py [N ...]      e.g. 755 44000
"""

import sys
import time

import torch


def main(counts: list[int], repeats: int = 200) -> None:
    print(f"{torch.get_num_threads()} threads; ms per training step (all groups)")
    for n in counts:
        shapes = [(n, 3), (n, 1, 3), (n, 15, 3), (n, 1), (n, 3), (n, 4)]
        for options in ({}, {"foreach": True}, {"fused": True}):
            params = [torch.nn.Parameter(torch.randn(s)) for s in shapes]
            adams = [torch.optim.Adam([p], lr=1e-3, eps=1e-15, **options) for p in params]
            for p in params:
                p.grad = torch.randn_like(p)
            for adam in adams:
                adam.step()
            start = time.perf_counter()
            for _ in range(repeats):
                for adam in adams:
                    adam.step()
            ms = 1000 * (time.perf_counter() - start) / repeats
            print(f"{n:>7} Gaussians  {str(options or 'default'):<18} {ms:.3f}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [755, 44000])
