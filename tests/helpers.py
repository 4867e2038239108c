"""Shared test helpers."""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence

import torch


def train_steps(
    model,
    cameras,
    images: Sequence[torch.Tensor],
    steps: int,
    after_step: Optional[Callable[[int], None]] = None,
    lrs: Optional[Dict[str, float]] = None,
) -> torch.Tensor:
    """The training loop of nerfstudio's trainer, reduced: one Adam per parameter group (lr 1e-3 or
    ``lrs[group]``),
    views in turn with their index in ``metadata["cam_idx"]`` as the datamanager sets it,
    ``step_post_backward`` (densification) after every step. Returns the last step's main loss;
    ``after_step(step)`` runs after each step."""
    lrs = lrs or {}
    opts = {k: torch.optim.Adam(p, lr=lrs.get(k, 1e-3)) for k, p in model.get_param_groups().items() if p}
    model.train()
    for step in range(steps):
        model.step, model.optimizers = step, opts
        i = step % len(images)
        camera = cameras[i : i + 1]
        camera.metadata = {"cam_idx": i}
        outputs = model.get_outputs(camera)
        loss = model.get_loss_dict(outputs, {"image": images[i]})["main_loss"]
        loss.backward()
        for opt in opts.values():
            opt.step()
            opt.zero_grad()
        model.step_post_backward(step)
        if after_step is not None:
            after_step(step)
    return loss
