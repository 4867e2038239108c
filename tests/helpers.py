"""Shared test helpers."""

from __future__ import annotations

from typing import Callable, Optional, Sequence

import torch


def train_steps(
    model,
    cameras,
    images: Sequence[torch.Tensor],
    steps: int,
    after_step: Optional[Callable[[int], None]] = None,
) -> torch.Tensor:
    """The training loop of nerfstudio's trainer, reduced: one Adam per Gaussian parameter group
    (lr 1e-3), views in turn, ``step_post_backward`` (densification) after every step. Returns the
    last step's main loss; ``after_step(step)`` runs after each step."""
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in model.gauss_params.items()}
    model.train()
    for step in range(steps):
        model.step, model.optimizers = step, opts
        i = step % len(images)
        outputs = model.get_outputs(cameras[i : i + 1])
        loss = model.get_loss_dict(outputs, {"image": images[i]})["main_loss"]
        loss.backward()
        for opt in opts.values():
            opt.step()
            opt.zero_grad()
        model.step_post_backward(step)
        if after_step is not None:
            after_step(step)
    return loss
