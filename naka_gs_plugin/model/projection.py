"""EWA projection of 3D Gaussians and their spherical-harmonic colours, in pure torch.

This reproduces the math of gsplat 1.4.0's ``fully_fused_projection`` (pinhole camera) and
``spherical_harmonics`` so that our CPU rasterizer sees exactly the screen-space Gaussians gsplat's
CUDA path would. gsplat only ships these as CUDA kernels plus private ``_torch_impl`` helpers
(meant for its tests, not a public API), so we keep our own copy here and cross-check it against
those helpers in ``tests/model/test_rasterize.py``.

Conventions (all as gsplat):

- quaternions are ``wxyz`` and need not be normalised; scales are already exponentiated;
- ``viewmats`` are world-to-camera 4x4 matrices in the OpenCV convention (x right, y down, the
  camera looks down +z); ``Ks`` are 3x3 pinhole intrinsics in pixels;
- screen-space quantities are in pixels; pixel ``(x, y)`` has its centre at ``(x + 0.5, y + 0.5)``;
- outputs of culled Gaussians (radius 0) are zero, and carry no gradient, as gsplat's kernels.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

# Real spherical-harmonic constants and signs of gsplat 1.4.0 (Sloan, "Efficient Spherical
# Harmonic Evaluation", JCGT 2013), degrees 0..3.
SH_C0 = 0.2820947917738781
SH_C1 = 0.48860251190292
SH_C2 = (1.092548430592079, 0.9461746957575601, 0.3153915652525201, 0.5462742152960395)
SH_C3 = (
    2.285228997322329,
    0.4570457994644658,
    1.445305721320277,
    0.5900435899266435,
    1.865881662950577,
    1.119528997770346,
)
MAX_SH_DEGREE = 3

JACOBIAN_FOV_MARGIN = 0.3
"""The Jacobian is evaluated with x/z, y/z clamped to the image plus 30 % of tan(fov/2) (gsplat)."""

RADIUS_SIGMAS = 3.0
"""Screen-space support radius in standard deviations of the blurred 2D Gaussian."""


class Projection(NamedTuple):
    """Per-camera screen-space Gaussians; entries with ``radii == 0`` are culled (zeros)."""

    radii: Int[Tensor, "C N"]
    means2d: Float[Tensor, "C N 2"]
    depths: Float[Tensor, "C N"]
    conics: Float[Tensor, "C N 3"]
    compensations: Optional[Float[Tensor, "C N"]]


class _SqrtWithEpsGrad(torch.autograd.Function):
    """``sqrt(x)`` for ``x >= 0`` whose gradient is ``0.5 / (sqrt(x) + 1e-6)`` (gsplat's add_blur_vjp).

    Plain autograd would give an infinite gradient at ``x = 0`` (a Gaussian with a zero scale).
    """

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        out = torch.sqrt(x)
        ctx.save_for_backward(out)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (out,) = ctx.saved_tensors
        return grad * 0.5 / (out + 1e-6)


def quat_to_rotmat(quats: Float[Tensor, "*batch 4"]) -> Float[Tensor, "*batch 3 3"]:
    """Rotation matrix of a ``wxyz`` quaternion, normalised first (a zero quaternion gives I)."""
    w, x, y, z = torch.unbind(F.normalize(quats, p=2, dim=-1), dim=-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return rot.reshape(quats.shape[:-1] + (3, 3))


def quat_scale_to_covar(quats: Float[Tensor, "N 4"], scales: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3 3"]:
    """World-space covariance ``R S S^T R^T`` from ``wxyz`` quaternions and (exp'ed) scales."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    calc_compensations: bool = False,
) -> Projection:
    """EWA-project 3D Gaussians into C pinhole cameras (gsplat 1.4.0 ``fully_fused_projection``).

    ``eps2d`` (px^2) is added to the diagonal of every 2D covariance; ``compensations`` (only when
    ``calc_compensations``) is ``sqrt(max(det_orig / det_blurred, 0))``, the opacity factor of the
    "antialiased" mode. ``radii`` is ``ceil(3 sqrt(lambda_max))`` px of the blurred covariance, or 0
    when the centre is nearer than ``near_plane``, farther than ``far_plane``, the blurred
    determinant is not positive (or not finite), or the radius box lies fully outside the image.
    """
    rot = viewmats[:, :3, :3]
    trans = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]
    covars = quat_scale_to_covar(quats, scales)
    covars_c = torch.einsum("cij,njk,clk->cnil", rot, covars, rot)

    x, y, z = torch.unbind(means_c, dim=-1)
    depth_ok = (z >= near_plane) & (z <= far_plane)
    # Culled entries get a harmless depth so that neither values nor gradients become inf/NaN.
    z = torch.where(depth_ok, z, torch.ones_like(z))

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + JACOBIAN_FOV_MARGIN * tan_fovx
    lim_x_neg = cx / fx + JACOBIAN_FOV_MARGIN * tan_fovx
    lim_y_pos = (height - cy) / fy + JACOBIAN_FOV_MARGIN * tan_fovy
    lim_y_neg = cy / fy + JACOBIAN_FOV_MARGIN * tan_fovy
    tx = z * torch.clamp(x / z, min=-lim_x_neg, max=lim_x_pos)
    ty = z * torch.clamp(y / z, min=-lim_y_neg, max=lim_y_pos)

    zeros = torch.zeros_like(z)
    jac = torch.stack([fx / z, zeros, -fx * tx / (z * z), zeros, fy / z, -fy * ty / (z * z)], dim=-1).reshape(
        z.shape + (2, 3)
    )
    cov2d = jac @ covars_c @ jac.transpose(-1, -2)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)

    cov_a, cov_b, cov_c = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det_orig = cov_a * cov_c - cov_b * cov_b
    cov_a = cov_a + eps2d
    cov_c = cov_c + eps2d
    det = cov_a * cov_c - cov_b * cov_b
    valid = depth_ok & (det > 0) & torch.isfinite(det)
    det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det, -cov_b / det, cov_a / det], dim=-1)

    with torch.no_grad():
        half_trace = 0.5 * (cov_a + cov_c)
        lambda_max = half_trace + torch.sqrt(torch.clamp(half_trace * half_trace - det, min=0.01))
        radius = torch.ceil(RADIUS_SIGMAS * torch.sqrt(lambda_max))
        mx, my = means2d[..., 0], means2d[..., 1]
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        keep = valid & inside
        radii = torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)

    compensations = None
    if calc_compensations:
        ratio = torch.clamp(det_orig / det, min=0.0)
        compensations = torch.where(keep, _SqrtWithEpsGrad.apply(ratio), torch.zeros_like(ratio))
    return Projection(
        radii=radii,
        means2d=torch.where(keep[..., None], means2d, torch.zeros_like(means2d)),
        depths=torch.where(keep, means_c[..., 2], torch.zeros_like(det)),
        conics=torch.where(keep[..., None], conics, torch.zeros_like(conics)),
        compensations=compensations,
    )


def sh_bases(degree: int, dirs: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch K"]:
    """Real SH basis values for ``degree`` in 0..3 at unit directions, ``K = (degree + 1)^2``.

    Ordering, constants and signs are gsplat 1.4.0's (``sh_coeffs_to_color_fast``).
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    bases = [torch.full_like(dirs[..., 0], SH_C0)]
    if degree >= 1:
        x, y, z = torch.unbind(dirs, dim=-1)
        bases += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        z2 = z * z
        fc1 = x * x - y * y
        fs1 = 2.0 * x * y
        bases += [
            SH_C2[3] * fs1,
            -SH_C2[0] * z * y,
            SH_C2[1] * z2 - SH_C2[2],
            -SH_C2[0] * z * x,
            SH_C2[3] * fc1,
        ]
    if degree >= 3:
        tmp_c = -SH_C3[0] * z2 + SH_C3[1]
        tmp_b = SH_C3[2] * z
        fc2 = x * fc1 - y * fs1
        fs2 = x * fs1 + y * fc1
        bases += [
            -SH_C3[3] * fs2,
            tmp_b * fs1,
            tmp_c * y,
            z * (SH_C3[4] * z2 - SH_C3[5]),
            tmp_c * x,
            tmp_b * fc1,
            -SH_C3[3] * fc2,
        ]
    return torch.stack(bases, dim=-1)


def spherical_harmonics(
    degree: int, dirs: Float[Tensor, "*batch 3"], coeffs: Float[Tensor, "*batch K 3"]
) -> Float[Tensor, "*batch 3"]:
    """Evaluate SH of ``degree`` along ``dirs`` (normalised here); uses the first (degree+1)^2 coeffs."""
    n_bases = (degree + 1) ** 2
    if coeffs.shape[-2] < n_bases:
        raise ValueError(f"sh degree {degree} needs {n_bases} coefficients, got {coeffs.shape[-2]}")
    if degree > 0:
        dirs = F.normalize(dirs, p=2, dim=-1)
    bases = sh_bases(degree, dirs)
    return (bases[..., None] * coeffs[..., :n_bases, :]).sum(dim=-2)


def sh_colors(
    means: Float[Tensor, "N 3"],
    coeffs: Float[Tensor, "C N K 3"],
    viewmats: Float[Tensor, "C 4 4"],
    degree: int,
) -> Float[Tensor, "C N 3"]:
    """View-dependent colour per camera, ``clamp(SH(means - camera centre) + 0.5, min=0)`` (gsplat)."""
    centres = torch.linalg.inv(viewmats)[:, :3, 3]
    dirs = means[None, :, :] - centres[:, None, :]
    return torch.clamp_min(spherical_harmonics(degree, dirs, coeffs) + 0.5, 0.0)


def pixel_bounds(
    means2d: Float[Tensor, "C N 2"], radii: Int[Tensor, "C N"], width: int, height: int
) -> Int[Tensor, "C N 4"]:
    """Inclusive pixel box ``(x_lo, x_hi, y_lo, y_hi)`` of each Gaussian, clipped to the image.

    Pixel ``x`` is in the box when its centre ``x + 0.5`` lies in ``[mean - radius, mean + radius]``
    (same for y). Culled Gaussians get an empty box (``lo > hi``). The sparse and the dense
    rasterizers both use this, so they composite exactly the same Gaussian-pixel pairs.
    """
    r = radii.to(means2d.dtype)
    mx, my = means2d[..., 0], means2d[..., 1]
    x_lo = torch.ceil(mx - r - 0.5).clamp(min=0)
    x_hi = torch.floor(mx + r - 0.5).clamp(max=width - 1)
    y_lo = torch.ceil(my - r - 0.5).clamp(min=0)
    y_hi = torch.floor(my + r - 0.5).clamp(max=height - 1)
    box = torch.stack([x_lo, x_hi, y_lo, y_hi], dim=-1)
    empty = torch.tensor([0.0, -1.0, 0.0, -1.0], dtype=box.dtype, device=box.device)
    return torch.where((radii > 0)[..., None], box, empty).to(torch.int64)
