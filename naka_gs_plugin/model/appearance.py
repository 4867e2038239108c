"""Per-view appearance: one colour transform per training image, the scene's average at novel views.

Each training target is enhanced on its own (Naka's per-image min-max stretch, a network on that image)
from a capture whose exposure also varies from view to view, so the same surface has a different
brightness and colour in different targets. A model with one colour per Gaussian fits that with
view-dependent colour and floaters in front of single cameras. Here each training view ``i`` gets a
per-channel gain and offset applied to its render during training only,

    rgb_i = rgb * exp(a_i - mean(a)) + (b_i - mean(b)),

with the means taken over the training views: the transforms average to the identity, so the Gaussians
hold the views' average appearance and every other camera (eval, viewer, export) renders it unchanged.
Unlike splatfacto's bilateral grid (a local affine per view and no constraint on its mean), this is
global per view: it absorbs exposure and white balance, not shading.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor, nn


class ViewAppearance(nn.Module):
    """Per-channel gain (log scale) and offset per training view, constrained to average the identity.

    Colours are display-referred sRGB in [0, 1] (what the rasterizer outputs and the targets hold).
    """

    def __init__(self, num_views: int) -> None:
        super().__init__()
        if num_views < 1:
            raise ValueError(f"per-view appearance needs at least one training view, got {num_views}")
        self.log_gain = nn.Parameter(torch.zeros(num_views, 3))
        self.offset = nn.Parameter(torch.zeros(num_views, 3))

    def transform(self, view: int) -> tuple[Float[Tensor, "3"], Float[Tensor, "3"]]:
        """(gain, offset) of training view ``view``: zero-mean log gains and offsets over all views."""
        if not 0 <= view < self.log_gain.shape[0]:
            raise IndexError(f"training view {view} out of range 0..{self.log_gain.shape[0] - 1}")
        # The means are constants to the gradient: a view's loss then moves only that view's transform
        # (through the means it would push every other view the opposite way, and Adam, normalising
        # those small pushes, made them as large as the view's own: the transforms drifted apart in
        # the order the views are visited).
        gain = torch.exp(self.log_gain[view] - self.log_gain.mean(0).detach())
        return gain, self.offset[view] - self.offset.mean(0).detach()

    def forward(self, rgb: Float[Tensor, "*batch 3"], view: int) -> Float[Tensor, "*batch 3"]:
        """``rgb`` as training view ``view`` saw it, clamped to [0, 1]."""
        gain, offset = self.transform(view)
        return torch.clamp(rgb * gain + offset, 0.0, 1.0)
