"""Splatfacto's SSIM loss forward and backward at one image size, as a training step runs it: the compiled
``SSIMLoss`` (naka_gs_plugin/model/ssim.py) and pytorch_msssim's module, on permuted HWC float32 images, the
prediction requiring a gradient, glibc's heap thresholds as training sets them (``keep_freed_memory``). Prints the
median ms of forward + backward over REPEATS calls, after 5 warm-up calls (numba's compile or cache load).
Run from the repository root (``PYTHONPATH=<tree>`` times another tree's kernels):

    .venv/bin/python docs/experiments/ssim_step.py [HEIGHT WIDTH [REPEATS]]    # default 375 500 60
"""

import sys
import time

import numpy as np
import torch
from pytorch_msssim import SSIM

from naka_gs_plugin.cpu import keep_freed_memory
from naka_gs_plugin.model.ssim import SSIMLoss


def median_ms(module, gt, pred, repeats):
    def step():
        pred.grad = None
        value = module(gt.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None])
        (1 - value).backward()

    for _ in range(5):
        step()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main(height=375, width=500, repeats=60):
    keep_freed_memory()
    gen = torch.Generator().manual_seed(0)
    gt = torch.rand(height, width, 3, generator=gen)
    pred = (gt + 0.1 * torch.randn(height, width, 3, generator=gen)).clamp(0, 1).requires_grad_(True)
    compiled = median_ms(SSIMLoss(data_range=1.0, channel=3), gt, pred, repeats)
    reference = median_ms(SSIM(data_range=1.0, channel=3), gt, pred, max(5, repeats // 6))
    print(
        f"{height}x{width}, {torch.get_num_threads()} threads: compiled SSIM {compiled:.2f} ms, "
        f"pytorch_msssim {reference:.1f} ms (forward + backward, median)"
    )


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
