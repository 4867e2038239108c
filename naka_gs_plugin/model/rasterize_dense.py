"""Dense reference rasterizer: every pixel against every Gaussian, plain autograd.

Slow and memory-hungry (pixels x Gaussians tensors) on purpose: it spells out gsplat 1.4.0's
compositing rule literally, with a running product of ``1 - alpha`` per pixel, and is used by the
tests (in float64) and by the benchmark as the baseline for :mod:`naka_gs_plugin.model.rasterize`.
It shares the projection (cross-checked against gsplat on its own) and the pixel box definition.
"""

from __future__ import annotations

from typing import Dict, Literal, Optional, Tuple

import torch
from jaxtyping import Float, Int
from torch import Tensor

from naka_gs_plugin.model.projection import pixel_bounds
from naka_gs_plugin.model.rasterize import (
    ALPHA_MAX,
    ALPHA_MIN,
    TRANSMITTANCE_MIN,
    RenderMode,
    rasterization_with_compositor,
)


def rasterize_to_pixels_dense(
    means2d: Float[Tensor, "C N 2"],
    conics: Float[Tensor, "C N 3"],
    colors: Float[Tensor, "C N D"],
    opacities: Float[Tensor, "C N"],
    depths: Float[Tensor, "C N"],
    radii: Int[Tensor, "C N"],
    width: int,
    height: int,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
) -> Tuple[Float[Tensor, "C H W D"], Float[Tensor, "C H W 1"]]:
    """Composite all Gaussians over all pixels, front to back, exactly as the sparse rasterizer."""
    renders, alphas = [], []
    ys, xs = torch.meshgrid(
        torch.arange(height, device=means2d.device),
        torch.arange(width, device=means2d.device),
        indexing="ij",
    )
    xs, ys = xs.reshape(-1, 1), ys.reshape(-1, 1)  # [P, 1] pixel indices
    box = pixel_bounds(means2d, radii, width, height)
    for cam in range(colors.shape[0]):
        order = torch.argsort(depths[cam], stable=True)  # front to back
        mean, conic = means2d[cam, order], conics[cam, order]
        opac, color, bx = opacities[cam, order], colors[cam, order], box[cam, order]

        dx = mean[None, :, 0] - (xs.to(mean.dtype) + 0.5)  # [P, N]
        dy = mean[None, :, 1] - (ys.to(mean.dtype) + 0.5)
        sigma = 0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) + conic[:, 1] * dx * dy
        alpha = torch.clamp_max(opac * torch.exp(-sigma), ALPHA_MAX)
        in_box = (xs >= bx[:, 0]) & (xs <= bx[:, 1]) & (ys >= bx[:, 2]) & (ys <= bx[:, 3])
        valid = in_box & (sigma >= 0) & (alpha >= ALPHA_MIN)
        alpha = torch.where(valid, alpha, torch.zeros_like(alpha))

        # gsplat stops a pixel before the Gaussian whose "next T" would be <= 1e-4.
        t_after = torch.cumprod(1.0 - alpha, dim=1)
        contributes = valid & (t_after > TRANSMITTANCE_MIN)
        alpha = torch.where(contributes, alpha, torch.zeros_like(alpha))
        t_incl = torch.cumprod(1.0 - alpha, dim=1)
        t_before = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
        weights = alpha * t_before
        t_final = t_incl[:, -1:] if t_incl.shape[1] > 0 else torch.ones_like(dx[:, :1])

        render = weights @ color
        if backgrounds is not None:
            render = render + t_final * backgrounds[cam]
        renders.append(render.reshape(height, width, -1))
        alphas.append((1.0 - t_final).reshape(height, width, 1))
    return torch.stack(renders), torch.stack(alphas)


def rasterization_dense(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, " N"],
    colors: Tensor,
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    sh_degree: Optional[int] = None,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    eps2d: float = 0.3,
) -> Tuple[Float[Tensor, "C H W X"], Float[Tensor, "C H W 1"], Dict]:
    """Same interface and result as :func:`naka_gs_plugin.model.rasterize.rasterization`
    (without ``absgrad``), computed densely."""
    return rasterization_with_compositor(
        rasterize_to_pixels_dense,
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        sh_degree=sh_degree,
        backgrounds=backgrounds,
        render_mode=render_mode,
        rasterize_mode=rasterize_mode,
        eps2d=eps2d,
    )
