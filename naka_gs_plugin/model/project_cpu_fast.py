"""Compiled CPU projection and SH colours for the cpu-fast rasterizer: numba, hand-written backward.

The same math as the readable pure-torch reference :mod:`naka_gs_plugin.model.projection` (gsplat
1.4.0 ``fully_fused_projection`` for pinhole cameras and ``spherical_harmonics`` with its
``clamp(SH + 0.5, min=0)`` colour), with the same conventions: ``wxyz`` quaternions of any norm,
exp'ed scales, OpenCV world-to-camera ``viewmats``, pixel units with pixel centres at ``+0.5``,
culled entries (radius 0) zero and without gradient. Eager torch spends most of its time here
materialising [C, N, 3, 3] intermediates and their autograd graph; these kernels make one pass over
the Gaussians (``prange``; each thread owns its Gaussians, so there are no races and the results do
not depend on the thread count) in the forward and one in the backward, recomputing what they need.

Everything is evaluated in float64 and rounded to the inputs' dtype at the end, so float32 results
can differ from the torch path's float32 arithmetic by rounding (~1e-7 relative); a radius or the
``alpha >= 1/255`` test of a pair can then flip only for values within rounding of a threshold.
The gradients are the torch path's autograd gradients, including its masks: ``clamp``'s gradient
passes at the bounds, ``F.normalize``'s ``max(norm, 1e-12)``, the ``0.5 / (sqrt + 1e-6)`` gradient
of the antialiasing compensation, and the SH colour clamp passing its gradient where
``SH + 0.5 >= 0``. Gradients w.r.t. ``viewmats`` and ``Ks`` are not implemented: when either
requires grad (camera optimisation), :func:`project_gaussians` and :func:`sh_colors` defer to the
torch reference.
"""

from __future__ import annotations

import math
from typing import Tuple, Union

import numpy as np
import torch
from jaxtyping import Float
from numba import njit, prange
from torch import Tensor

from naka_gs_plugin.cpu import untraced
from naka_gs_plugin.model import projection as reference
from naka_gs_plugin.model.projection import (
    JACOBIAN_FOV_MARGIN,
    MAX_SH_DEGREE,
    RADIUS_SIGMAS,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
    Projection,
)

NORMALIZE_EPS = 1e-12
"""``F.normalize``'s default ``eps``: the norm is clamped to at least this."""

COMPENSATION_GRAD_EPS = 1e-6
"""Gradient of the compensation ``sqrt(r)`` is ``0.5 / (sqrt(r) + 1e-6)`` (gsplat's add_blur_vjp)."""

INT32_MAX = 2147483647.0
"""Radii are int32; larger radii (beyond any image) are clamped to this."""

_CHUNK = 256
"""Gaussians per ``prange`` iteration of the SH kernels (each allocates its small scratch once)."""


@njit(cache=True, inline="always")
def _rotmat(qw, qx, qy, qz):
    """Rotation matrix (row-major 9-tuple) of the normalised quaternion and the normalised quaternion."""
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    d = max(norm, NORMALIZE_EPS)
    w, x, y, z = qw / d, qx / d, qy / d, qz / d
    rot = (
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )
    return rot, w, x, y, z, norm


@njit(cache=True, inline="always")
def _camera(viewmats, Ks, c, width, height):
    """Rotation (9-tuple), translation, intrinsics and Jacobian clamp limits of camera ``c``."""
    v = viewmats[c]
    rc = (v[0, 0], v[0, 1], v[0, 2], v[1, 0], v[1, 1], v[1, 2], v[2, 0], v[2, 1], v[2, 2])
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lims = (
        (width - cx) / fx + JACOBIAN_FOV_MARGIN * tan_fovx,
        cx / fx + JACOBIAN_FOV_MARGIN * tan_fovx,
        (height - cy) / fy + JACOBIAN_FOV_MARGIN * tan_fovy,
        cy / fy + JACOBIAN_FOV_MARGIN * tan_fovy,
    )
    return rc, (v[0, 3], v[1, 3], v[2, 3]), (fx, fy, cx, cy), lims


@njit(cache=True, inline="always")
def _screen(m, rc, t, intr, lims, mm, eps2d):
    """Camera-space mean, clamped x/z and y/z (and whether the clamps pass gradients), the rows of
    ``V = J R_cam M`` and the blurred 2D covariance ``(a, b, c)``, its determinant and the
    unblurred determinant."""
    fx, fy = intr[0], intr[1]
    x = rc[0] * m[0] + rc[1] * m[1] + rc[2] * m[2] + t[0]
    y = rc[3] * m[0] + rc[4] * m[1] + rc[5] * m[2] + t[1]
    z = rc[6] * m[0] + rc[7] * m[1] + rc[8] * m[2] + t[2]
    u, v = x / z, y / z
    u_pass = -lims[1] <= u <= lims[0]
    v_pass = -lims[3] <= v <= lims[2]
    uc = min(max(u, -lims[1]), lims[0])
    vc = min(max(v, -lims[3]), lims[2])
    # J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]] with tx = z * uc: -fx tx / z^2 = -fx uc / z.
    j00, j02 = fx / z, -fx * (z * uc) / (z * z)
    j11, j12 = fy / z, -fy * (z * vc) / (z * z)
    w0 = (j00 * rc[0] + j02 * rc[6], j00 * rc[1] + j02 * rc[7], j00 * rc[2] + j02 * rc[8])
    w1 = (j11 * rc[3] + j12 * rc[6], j11 * rc[4] + j12 * rc[7], j11 * rc[5] + j12 * rc[8])
    v0 = (
        w0[0] * mm[0] + w0[1] * mm[3] + w0[2] * mm[6],
        w0[0] * mm[1] + w0[1] * mm[4] + w0[2] * mm[7],
        w0[0] * mm[2] + w0[1] * mm[5] + w0[2] * mm[8],
    )
    v1 = (
        w1[0] * mm[0] + w1[1] * mm[3] + w1[2] * mm[6],
        w1[0] * mm[1] + w1[1] * mm[4] + w1[2] * mm[7],
        w1[0] * mm[2] + w1[1] * mm[5] + w1[2] * mm[8],
    )
    a0 = v0[0] * v0[0] + v0[1] * v0[1] + v0[2] * v0[2]
    b0 = v0[0] * v1[0] + v0[1] * v1[1] + v0[2] * v1[2]
    c0 = v1[0] * v1[0] + v1[1] * v1[1] + v1[2] * v1[2]
    a, c = a0 + eps2d, c0 + eps2d
    det = a * c - b0 * b0
    return (x, y, z), (uc, vc, u_pass, v_pass), (w0, w1, v0, v1), (a0, b0, c0), (a, c, det)


@njit(cache=True)
def _project_range(
    lo, hi, means, quats, scales, viewmats, Ks, width, height, eps2d, near, far, max_finite, radii, means2d, depths,
    conics, comps,
):  # fmt: skip
    """:func:`_project_forward` for Gaussians ``lo..hi-1`` (a function of its own: numba's parfor
    analysis does not handle the tuples; one call per chunk keeps the call overhead small)."""
    for n in range(lo, hi):
        _project_one(
            n, means, quats, scales, viewmats, Ks, width, height, eps2d, near, far, max_finite,
            radii, means2d, depths, conics, comps,
        )  # fmt: skip


@njit(cache=True, inline="always")
def _project_one(
    n, means, quats, scales, viewmats, Ks, width, height, eps2d, near, far, max_finite, radii, means2d, depths,
    conics, comps,
):  # fmt: skip
    """Project Gaussian ``n`` into every camera."""
    n_cams = viewmats.shape[0]
    calc_comp = comps.shape[0] == n_cams
    rot = _rotmat(np.float64(quats[n, 0]), np.float64(quats[n, 1]), np.float64(quats[n, 2]), np.float64(quats[n, 3]))[0]
    s = (np.float64(scales[n, 0]), np.float64(scales[n, 1]), np.float64(scales[n, 2]))
    mm = (
        rot[0] * s[0], rot[1] * s[1], rot[2] * s[2],
        rot[3] * s[0], rot[4] * s[1], rot[5] * s[2],
        rot[6] * s[0], rot[7] * s[1], rot[8] * s[2],
    )  # fmt: skip
    m = (np.float64(means[n, 0]), np.float64(means[n, 1]), np.float64(means[n, 2]))
    for c in range(n_cams):
        rc, t, intr, lims = _camera(viewmats, Ks, c, width, height)
        mc, _, _, cov0, cov = _screen(m, rc, t, intr, lims, mm, eps2d)
        a, cc, det = cov
        mx = intr[0] * mc[0] / mc[2] + intr[2]
        my = intr[1] * mc[1] / mc[2] + intr[3]
        keep = near <= mc[2] <= far and det > 0 and det <= max_finite
        radius = 0.0
        if keep:
            half_trace = 0.5 * (a + cc)
            lambda_max = half_trace + math.sqrt(max(half_trace * half_trace - det, 0.01))
            radius = np.ceil(RADIUS_SIGMAS * math.sqrt(lambda_max))
            keep = mx + radius > 0 and mx - radius < width and my + radius > 0 and my - radius < height
        if not keep:
            radii[c, n] = 0
            means2d[c, n, 0] = means2d[c, n, 1] = depths[c, n] = 0.0
            conics[c, n, 0] = conics[c, n, 1] = conics[c, n, 2] = 0.0
            if calc_comp:
                comps[c, n] = 0.0
            continue
        radii[c, n] = np.int32(min(radius, INT32_MAX))
        means2d[c, n, 0], means2d[c, n, 1] = mx, my
        depths[c, n] = mc[2]
        conics[c, n, 0], conics[c, n, 1], conics[c, n, 2] = cc / det, -cov0[1] / det, a / det
        if calc_comp:
            comps[c, n] = math.sqrt(max((cov0[0] * cov0[2] - cov0[1] * cov0[1]) / det, 0.0))


@njit(parallel=True, cache=True)
def _project_forward(
    means, quats, scales, viewmats, Ks, width, height, eps2d, near, far, max_finite, radii, means2d, depths, conics,
    comps,
):  # fmt: skip
    """Fill ``radii`` [C,N], ``means2d`` [C,N,2], ``depths`` [C,N], ``conics`` [C,N,3] and, when it
    has C rows, ``comps`` [C,N] (zeros for culled entries)."""
    n_gauss = means.shape[0]
    for chunk in prange((n_gauss + _CHUNK - 1) // _CHUNK):
        _project_range(
            chunk * _CHUNK, min((chunk + 1) * _CHUNK, n_gauss), means, quats, scales, viewmats, Ks, width, height,
            eps2d, near, far, max_finite, radii, means2d, depths, conics, comps,
        )  # fmt: skip


@njit(cache=True)
def _project_range_backward(
    lo, hi, means, quats, scales, viewmats, Ks, width, height, eps2d, radii, g_means2d, g_depths, g_conics, g_comps,
    g_means, g_quats, g_scales,
):  # fmt: skip
    """:func:`_project_backward` for Gaussians ``lo..hi-1``."""
    for n in range(lo, hi):
        _project_one_backward(
            n, means, quats, scales, viewmats, Ks, width, height, eps2d, radii, g_means2d, g_depths, g_conics,
            g_comps, g_means, g_quats, g_scales,
        )  # fmt: skip


@njit(cache=True, inline="always")
def _project_one_backward(
    n, means, quats, scales, viewmats, Ks, width, height, eps2d, radii, g_means2d, g_depths, g_conics, g_comps,
    g_means, g_quats, g_scales,
):  # fmt: skip
    """Gradients of Gaussian ``n`` (zero rows, as written by the caller, when culled everywhere)."""
    n_cams = viewmats.shape[0]
    calc_comp = g_comps.shape[0] == n_cams
    rot, qw, qx, qy, qz, qnorm = _rotmat(
        np.float64(quats[n, 0]), np.float64(quats[n, 1]), np.float64(quats[n, 2]), np.float64(quats[n, 3])
    )
    s = (np.float64(scales[n, 0]), np.float64(scales[n, 1]), np.float64(scales[n, 2]))
    mm = (
        rot[0] * s[0], rot[1] * s[1], rot[2] * s[2],
        rot[3] * s[0], rot[4] * s[1], rot[5] * s[2],
        rot[6] * s[0], rot[7] * s[1], rot[8] * s[2],
    )  # fmt: skip
    m = (np.float64(means[n, 0]), np.float64(means[n, 1]), np.float64(means[n, 2]))
    gm0 = gm1 = gm2 = 0.0
    # dL/dM, M = R diag(s), row-major.
    gmm0 = gmm1 = gmm2 = gmm3 = gmm4 = gmm5 = gmm6 = gmm7 = gmm8 = 0.0
    touched = False
    for c in range(n_cams):
        if radii[c, n] == 0:
            continue
        touched = True
        rc, t, intr, lims = _camera(viewmats, Ks, c, width, height)
        fx, fy = intr[0], intr[1]
        mc, clamp, wv, cov0, cov = _screen(m, rc, t, intr, lims, mm, eps2d)
        x, y, z = mc
        uc, vc, u_pass, v_pass = clamp
        w0, w1, v0, v1 = wv
        a0, b0, c0 = cov0
        a, cc, det = cov
        # conics = (c/det, -b/det, a/det), det = a c - b^2.
        gc0, gc1, gc2 = np.float64(g_conics[c, n, 0]), np.float64(g_conics[c, n, 1]), np.float64(g_conics[c, n, 2])
        inv_det = 1.0 / det
        g_det = -(gc0 * cc - gc1 * b0 + gc2 * a) * inv_det * inv_det
        g_det_orig = 0.0
        if calc_comp:
            ratio = (a0 * c0 - b0 * b0) * inv_det
            if ratio >= 0:
                g_ratio = np.float64(g_comps[c, n]) * 0.5 / (math.sqrt(ratio) + COMPENSATION_GRAD_EPS)
                g_det_orig = g_ratio * inv_det
                g_det -= g_ratio * ratio * inv_det
        g_a0 = gc2 * inv_det + g_det * cc + g_det_orig * c0
        g_c0 = gc0 * inv_det + g_det * a + g_det_orig * a0
        g_b0 = -gc1 * inv_det - 2.0 * b0 * (g_det + g_det_orig)
        # cov2d = V V^T, V = W M, W = J R_cam (rows w0, w1).
        gv0 = (2.0 * g_a0 * v0[0] + g_b0 * v1[0], 2.0 * g_a0 * v0[1] + g_b0 * v1[1], 2.0 * g_a0 * v0[2] + g_b0 * v1[2])
        gv1 = (g_b0 * v0[0] + 2.0 * g_c0 * v1[0], g_b0 * v0[1] + 2.0 * g_c0 * v1[1], g_b0 * v0[2] + 2.0 * g_c0 * v1[2])
        gmm0 += w0[0] * gv0[0] + w1[0] * gv1[0]
        gmm1 += w0[0] * gv0[1] + w1[0] * gv1[1]
        gmm2 += w0[0] * gv0[2] + w1[0] * gv1[2]
        gmm3 += w0[1] * gv0[0] + w1[1] * gv1[0]
        gmm4 += w0[1] * gv0[1] + w1[1] * gv1[1]
        gmm5 += w0[1] * gv0[2] + w1[1] * gv1[2]
        gmm6 += w0[2] * gv0[0] + w1[2] * gv1[0]
        gmm7 += w0[2] * gv0[1] + w1[2] * gv1[1]
        gmm8 += w0[2] * gv0[2] + w1[2] * gv1[2]
        gw0 = (
            gv0[0] * mm[0] + gv0[1] * mm[1] + gv0[2] * mm[2],
            gv0[0] * mm[3] + gv0[1] * mm[4] + gv0[2] * mm[5],
            gv0[0] * mm[6] + gv0[1] * mm[7] + gv0[2] * mm[8],
        )
        gw1 = (
            gv1[0] * mm[0] + gv1[1] * mm[1] + gv1[2] * mm[2],
            gv1[0] * mm[3] + gv1[1] * mm[4] + gv1[2] * mm[5],
            gv1[0] * mm[6] + gv1[1] * mm[7] + gv1[2] * mm[8],
        )
        g_j00 = gw0[0] * rc[0] + gw0[1] * rc[1] + gw0[2] * rc[2]
        g_j02 = gw0[0] * rc[6] + gw0[1] * rc[7] + gw0[2] * rc[8]
        g_j11 = gw1[0] * rc[3] + gw1[1] * rc[4] + gw1[2] * rc[5]
        g_j12 = gw1[0] * rc[6] + gw1[1] * rc[7] + gw1[2] * rc[8]
        # J entries: fx/z, -fx tx/z^2, fy/z, -fy ty/z^2 with tx = z clamp(x/z), ty likewise.
        tx, ty = z * uc, z * vc
        z2 = z * z
        g_z = -(g_j00 * fx + g_j11 * fy) / z2 + 2.0 * (g_j02 * fx * tx + g_j12 * fy * ty) / (z2 * z)
        g_tx, g_ty = -g_j02 * fx / z2, -g_j12 * fy / z2
        g_x = g_y = 0.0
        g_z += g_tx * uc + g_ty * vc
        if u_pass:
            g_x += g_tx
            g_z -= g_tx * x / z
        if v_pass:
            g_y += g_ty
            g_z -= g_ty * y / z
        # means2d = (fx x/z + cx, fy y/z + cy), depth = z.
        gx2, gy2 = np.float64(g_means2d[c, n, 0]), np.float64(g_means2d[c, n, 1])
        g_x += gx2 * fx / z
        g_y += gy2 * fy / z
        g_z += -(gx2 * fx * x + gy2 * fy * y) / z2 + np.float64(g_depths[c, n])
        gm0 += rc[0] * g_x + rc[3] * g_y + rc[6] * g_z
        gm1 += rc[1] * g_x + rc[4] * g_y + rc[7] * g_z
        gm2 += rc[2] * g_x + rc[5] * g_y + rc[8] * g_z
    if not touched:
        for q in range(4):
            g_quats[n, q] = 0.0
        for q in range(3):
            g_means[n, q] = g_scales[n, q] = 0.0
        return
    g_means[n, 0], g_means[n, 1], g_means[n, 2] = gm0, gm1, gm2
    gmm = (gmm0, gmm1, gmm2, gmm3, gmm4, gmm5, gmm6, gmm7, gmm8)
    g_scales[n, 0] = gmm[0] * rot[0] + gmm[3] * rot[3] + gmm[6] * rot[6]
    g_scales[n, 1] = gmm[1] * rot[1] + gmm[4] * rot[4] + gmm[7] * rot[7]
    g_scales[n, 2] = gmm[2] * rot[2] + gmm[5] * rot[5] + gmm[8] * rot[8]
    g = (
        gmm[0] * s[0], gmm[1] * s[1], gmm[2] * s[2],
        gmm[3] * s[0], gmm[4] * s[1], gmm[5] * s[2],
        gmm[6] * s[0], gmm[7] * s[1], gmm[8] * s[2],
    )  # fmt: skip
    w, x, y, z = qw, qx, qy, qz
    gw = 2.0 * (-z * g[1] + y * g[2] + z * g[3] - x * g[5] - y * g[6] + x * g[7])
    gx = 2.0 * (y * g[1] + z * g[2] + y * g[3] - 2.0 * x * g[4] - w * g[5] + z * g[6] + w * g[7] - 2.0 * x * g[8])
    gy = 2.0 * (-2.0 * y * g[0] + x * g[1] + w * g[2] + x * g[3] + z * g[5] - w * g[6] + z * g[7] - 2.0 * y * g[8])
    gz = 2.0 * (-2.0 * z * g[0] - w * g[1] + x * g[2] + w * g[3] - 2.0 * z * g[4] + y * g[5] + x * g[6] + y * g[7])
    # F.normalize: q / max(|q|, eps); the norm's gradient is cut below eps.
    if qnorm >= NORMALIZE_EPS:
        dot = w * gw + x * gx + y * gy + z * gz
        g_quats[n, 0] = (gw - w * dot) / qnorm
        g_quats[n, 1] = (gx - x * dot) / qnorm
        g_quats[n, 2] = (gy - y * dot) / qnorm
        g_quats[n, 3] = (gz - z * dot) / qnorm
    else:
        g_quats[n, 0], g_quats[n, 1] = gw / NORMALIZE_EPS, gx / NORMALIZE_EPS
        g_quats[n, 2], g_quats[n, 3] = gy / NORMALIZE_EPS, gz / NORMALIZE_EPS


@njit(parallel=True, cache=True)
def _project_backward(
    means, quats, scales, viewmats, Ks, width, height, eps2d, radii, g_means2d, g_depths, g_conics, g_comps,
    g_means, g_quats, g_scales,
):  # fmt: skip
    """Write the gradients w.r.t. means [N,3], quats [N,4] and scales [N,3] (in their dtype) of the
    kept entries' means2d, depths, conics and (when ``g_comps`` has C rows) compensations."""
    n_gauss = means.shape[0]
    for chunk in prange((n_gauss + _CHUNK - 1) // _CHUNK):
        _project_range_backward(
            chunk * _CHUNK, min((chunk + 1) * _CHUNK, n_gauss), means, quats, scales, viewmats, Ks, width, height,
            eps2d, radii, g_means2d, g_depths, g_conics, g_comps, g_means, g_quats, g_scales,
        )  # fmt: skip


@njit(cache=True, inline="always")
def _sh_bases(degree, x, y, z, out):
    """Fill ``out[:(degree+1)^2]`` with gsplat's real SH basis at the unit direction (x, y, z)."""
    out[0] = SH_C0
    if degree < 1:
        return
    out[1], out[2], out[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if degree < 2:
        return
    z2, fc1, fs1 = z * z, x * x - y * y, 2.0 * x * y
    out[4] = SH_C2[3] * fs1
    out[5] = -SH_C2[0] * z * y
    out[6] = SH_C2[1] * z2 - SH_C2[2]
    out[7] = -SH_C2[0] * z * x
    out[8] = SH_C2[3] * fc1
    if degree < 3:
        return
    tmp_c = -SH_C3[0] * z2 + SH_C3[1]
    tmp_b = SH_C3[2] * z
    out[9] = -SH_C3[3] * (x * fs1 + y * fc1)
    out[10] = tmp_b * fs1
    out[11] = tmp_c * y
    out[12] = z * (SH_C3[4] * z2 - SH_C3[5])
    out[13] = tmp_c * x
    out[14] = tmp_b * fc1
    out[15] = -SH_C3[3] * (x * fc1 - y * fs1)


@njit(cache=True, inline="always")
def _sh_bases_vjp(degree, x, y, z, g):
    """``sum_k g[k] d basis_k / d(x, y, z)`` for the bases of :func:`_sh_bases`."""
    gx = gy = gz = 0.0
    if degree < 1:
        return gx, gy, gz
    gx += -SH_C1 * g[3]
    gy += -SH_C1 * g[1]
    gz += SH_C1 * g[2]
    if degree < 2:
        return gx, gy, gz
    gx += 2.0 * SH_C2[3] * (y * g[4] + x * g[8]) - SH_C2[0] * z * g[7]
    gy += 2.0 * SH_C2[3] * (x * g[4] - y * g[8]) - SH_C2[0] * z * g[5]
    gz += -SH_C2[0] * (y * g[5] + x * g[7]) + 2.0 * SH_C2[1] * z * g[6]
    if degree < 3:
        return gx, gy, gz
    tmp_c = -SH_C3[0] * z * z + SH_C3[1]
    fc1, fs1 = x * x - y * y, 2.0 * x * y
    d_fc2_dx = 3.0 * (x * x - y * y)  # fc2 = x^3 - 3 x y^2
    gx += -SH_C3[3] * (6.0 * x * y * g[9] + d_fc2_dx * g[15])
    gy += -SH_C3[3] * (d_fc2_dx * g[9] - 6.0 * x * y * g[15])
    gx += 2.0 * SH_C3[2] * z * (y * g[10] + x * g[14]) + tmp_c * g[13]
    gy += 2.0 * SH_C3[2] * z * (x * g[10] - y * g[14]) + tmp_c * g[11]
    gz += SH_C3[2] * (fs1 * g[10] + fc1 * g[14]) - 2.0 * SH_C3[0] * z * (y * g[11] + x * g[13])
    gz += (3.0 * SH_C3[4] * z * z - SH_C3[5]) * g[12]
    return gx, gy, gz


@njit(cache=True, inline="always")
def _sh_dir(means, centres, n, c, degree):
    """Normalised view direction (as ``F.normalize``), its unnormalised vector and norm."""
    dx = np.float64(means[n, 0]) - centres[c, 0]
    dy = np.float64(means[n, 1]) - centres[c, 1]
    dz = np.float64(means[n, 2]) - centres[c, 2]
    if degree == 0:
        return (0.0, 0.0, 0.0), 1.0
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    d = max(norm, NORMALIZE_EPS)
    return (dx / d, dy / d, dz / d), norm


@njit(cache=True, inline="always")
def _sh_sums(bases, dc, rest, n_bases):
    """The three channels' ``sum_k bases[k] * coef[k, ch]`` (float64) of the coefficients ``dc`` [3] (k = 0)
    and ``rest`` [K - 1, 3] (k >= 1), in one pass over the bases, each channel summed in the order of ``k``."""
    s0 = s1 = s2 = 0.0
    s0 += bases[0] * dc[0]
    s1 += bases[0] * dc[1]
    s2 += bases[0] * dc[2]
    for k in range(1, n_bases):
        s0 += bases[k] * rest[k - 1, 0]
        s1 += bases[k] * rest[k - 1, 1]
        s2 += bases[k] * rest[k - 1, 2]
    return s0, s1, s2


@njit(parallel=True, cache=True)
def _sh_forward(means, dc, rest, centres, degree, out):
    """``out`` [C,N,3] = max(SH(means - centre_c) + 0.5, 0); coefficients ``dc`` [1 or C, N, 3] (degree 0)
    and ``rest`` [1 or C, N, K - 1, 3] (the higher degrees: splatfacto's two parameters, not concatenated)."""
    n_gauss, n_cams = means.shape[0], centres.shape[0]
    n_bases = (degree + 1) ** 2
    for chunk in prange((n_gauss + _CHUNK - 1) // _CHUNK):
        bases = np.empty(16)
        for n in range(chunk * _CHUNK, min((chunk + 1) * _CHUNK, n_gauss)):
            for c in range(n_cams):
                dirn, _ = _sh_dir(means, centres, n, c, degree)
                _sh_bases(degree, dirn[0], dirn[1], dirn[2], bases)
                m = c if dc.shape[0] > 1 else 0
                s0, s1, s2 = _sh_sums(bases, dc[m, n], rest[m, n], n_bases)
                out[c, n, 0], out[c, n, 1], out[c, n, 2] = max(s0 + 0.5, 0.0), max(s1 + 0.5, 0.0), max(s2 + 0.5, 0.0)


@njit(parallel=True, cache=True)
def _sh_backward(means, dc, rest, centres, degree, g_out, g_means, g_dc, g_rest):
    """Write the gradients of :func:`_sh_forward` w.r.t. means [N,3], ``dc`` and ``rest`` (in their dtype;
    coefficients beyond the degree get zeros). A camera whose ``g_out`` row is zero
    (a Gaussian it does not composite) is skipped: all its terms are +0, so the sums are the same
    bits (only non-finite coefficients, whose product with 0 torch would turn into NaN, differ)."""
    n_gauss, n_cams = means.shape[0], centres.shape[0]
    n_bases = (degree + 1) ** 2
    shared = dc.shape[0] == 1
    for chunk in prange((n_gauss + _CHUNK - 1) // _CHUNK):
        bases = np.empty(16)
        g_bases = np.empty(16)
        for n in range(chunk * _CHUNK, min((chunk + 1) * _CHUNK, n_gauss)):
            g_dc[:, n] = 0.0
            g_rest[:, n] = 0.0
            gm0 = gm1 = gm2 = 0.0
            for c in range(n_cams):
                g0, g1, g2 = np.float64(g_out[c, n, 0]), np.float64(g_out[c, n, 1]), np.float64(g_out[c, n, 2])
                if g0 == 0.0 and g1 == 0.0 and g2 == 0.0:
                    continue
                dirn, norm = _sh_dir(means, centres, n, c, degree)
                _sh_bases(degree, dirn[0], dirn[1], dirn[2], bases)
                m = c if not shared else 0
                s0, s1, s2 = _sh_sums(bases, dc[m, n], rest[m, n], n_bases)
                # clamp_min passes the gradient where SH + 0.5 >= 0 (and NaN, as torch does); a channel it
                # stops adds +-0 below, the same bits as no term. Indexed without views of the coefficient
                # rows and without branches in the loop over k, which LLVM then unrolls.
                h0 = g0 if not s0 + 0.5 < 0.0 else 0.0
                h1 = g1 if not s1 + 0.5 < 0.0 else 0.0
                h2 = g2 if not s2 + 0.5 < 0.0 else 0.0
                b = bases[0]
                g_dc[m, n, 0] += b * h0
                g_dc[m, n, 1] += b * h1
                g_dc[m, n, 2] += b * h2
                g_bases[0] = dc[m, n, 0] * h0 + dc[m, n, 1] * h1 + dc[m, n, 2] * h2
                for k in range(1, n_bases):
                    b = bases[k]
                    g_rest[m, n, k - 1, 0] += b * h0
                    g_rest[m, n, k - 1, 1] += b * h1
                    g_rest[m, n, k - 1, 2] += b * h2
                    g_bases[k] = rest[m, n, k - 1, 0] * h0 + rest[m, n, k - 1, 1] * h1 + rest[m, n, k - 1, 2] * h2
                if degree == 0:
                    continue
                gx, gy, gz = _sh_bases_vjp(degree, dirn[0], dirn[1], dirn[2], g_bases)
                if norm < NORMALIZE_EPS:  # F.normalize divides by eps; the norm gets no gradient
                    gm0 += gx / NORMALIZE_EPS
                    gm1 += gy / NORMALIZE_EPS
                    gm2 += gz / NORMALIZE_EPS
                    continue
                dot = dirn[0] * gx + dirn[1] * gy + dirn[2] * gz
                gm0 += (gx - dirn[0] * dot) / norm
                gm1 += (gy - dirn[1] * dot) / norm
                gm2 += (gz - dirn[2] * dot) / norm
            g_means[n, 0], g_means[n, 1], g_means[n, 2] = gm0, gm1, gm2


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _ProjectFn(torch.autograd.Function):
    """Numba EWA projection; outputs radii, means2d, depths, conics, compensations ([0, N] if off)."""

    @staticmethod
    @untraced()
    def forward(ctx, means, quats, scales, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_comp):
        n_cams, n = viewmats.shape[0], means.shape[0]
        dtype = means.dtype
        radii = torch.empty(n_cams, n, dtype=torch.int32)
        means2d = torch.empty(n_cams, n, 2, dtype=dtype)
        depths = torch.empty(n_cams, n, dtype=dtype)
        conics = torch.empty(n_cams, n, 3, dtype=dtype)
        comps = torch.empty(n_cams if calc_comp else 0, n, dtype=dtype)
        cams = (_np(viewmats.double()), _np(Ks.double()))
        args = (_np(means), _np(quats), _np(scales)) + cams + (width, height, float(eps2d))
        max_finite = float(torch.finfo(dtype).max)
        outs = (t.numpy() for t in (radii, means2d, depths, conics, comps))
        _project_forward(*args, float(near_plane), float(far_plane), max_finite, *outs)
        ctx.mark_non_differentiable(radii)
        ctx.save_for_backward(means, quats, scales, radii)
        ctx.cams = cams
        ctx.consts = (width, height, float(eps2d), calc_comp)
        return radii, means2d, depths, conics, comps

    @staticmethod
    @untraced()
    def backward(ctx, _g_radii, g_means2d, g_depths, g_conics, g_comps):
        means, quats, scales, radii = ctx.saved_tensors
        width, height, eps2d, calc_comp = ctx.consts
        g_means, g_quats, g_scales = (torch.empty(t.shape, dtype=t.dtype) for t in (means, quats, scales))
        _project_backward(
            _np(means), _np(quats), _np(scales), *ctx.cams, width, height, eps2d, radii.numpy(),
            _np(g_means2d), _np(g_depths), _np(g_conics), _np(g_comps),
            g_means.numpy(), g_quats.numpy(), g_scales.numpy(),
        )  # fmt: skip
        return g_means, g_quats, g_scales, None, None, None, None, None, None, None, None


class _SHFn(torch.autograd.Function):
    """Numba SH colours ``max(SH + 0.5, 0)`` per camera from coefficients ``dc`` [1 or C, N, 3] and
    ``rest`` [1 or C, N, K - 1, 3]."""

    @staticmethod
    @untraced()
    def forward(ctx, means, dc, rest, centres, degree):
        out = torch.empty(centres.shape[0], means.shape[0], 3, dtype=dc.dtype)
        _sh_forward(_np(means), _np(dc), _np(rest), _np(centres), degree, out.numpy())
        ctx.save_for_backward(means, dc, rest, centres)
        ctx.degree = degree
        return out

    @staticmethod
    @untraced()
    def backward(ctx, g_out):
        means, dc, rest, centres = ctx.saved_tensors
        g_means = torch.empty(means.shape, dtype=means.dtype)
        g_dc, g_rest = torch.empty(dc.shape, dtype=dc.dtype), torch.empty(rest.shape, dtype=rest.dtype)
        _sh_backward(
            _np(means), _np(dc), _np(rest), _np(centres), ctx.degree, _np(g_out), g_means.numpy(), g_dc.numpy(),
            g_rest.numpy(),
        )  # fmt: skip
        return g_means if ctx.degree > 0 else None, g_dc, g_rest, None, None


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
    """:func:`naka_gs_plugin.model.projection.project_gaussians` with compiled kernels (CPU tensors,
    float32/float64); the torch reference when ``viewmats`` or ``Ks`` require grad."""
    if viewmats.requires_grad or Ks.requires_grad:
        return reference.project_gaussians(
            means, quats, scales, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_compensations
        )
    radii, means2d, depths, conics, comps = _ProjectFn.apply(
        means, quats, scales, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_compensations
    )
    return Projection(radii, means2d, depths, conics, comps if calc_compensations else None)


def sh_colors(
    means: Float[Tensor, "N 3"],
    coeffs: Union[Float[Tensor, "C N K 3"], Tuple[Float[Tensor, "N 3"], Float[Tensor, "N K1 3"]]],
    viewmats: Float[Tensor, "C 4 4"],
    degree: int,
) -> Float[Tensor, "C N 3"]:
    """:func:`naka_gs_plugin.model.projection.sh_colors` with compiled kernels; ``coeffs`` may also
    be [N, K, 3] (shared by the cameras), or splatfacto's two parameters ``(features_dc [N, 3],
    features_rest [N, K - 1, 3])`` as they are: their [N, K, 3] concatenation, a copy of every coefficient
    forward and of its gradient backward, is then never made. The torch reference when ``viewmats``
    requires grad."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    n_bases = (degree + 1) ** 2
    if isinstance(coeffs, tuple):
        dc, rest = coeffs
        n_given = rest.shape[-2] + 1
    else:
        dc, rest = coeffs[..., 0, :], coeffs[..., 1:, :]
        n_given = coeffs.shape[-2]
    if n_given < n_bases:
        raise ValueError(f"sh degree {degree} needs {n_bases} coefficients, got {n_given}")
    if viewmats.requires_grad:
        coeffs = torch.cat((dc[..., None, :], rest), dim=-2)
        if coeffs.dim() == 3:
            coeffs = coeffs.expand(viewmats.shape[0], *coeffs.shape)
        return reference.sh_colors(means, coeffs, viewmats, degree)
    centres = torch.linalg.inv(viewmats.detach().double())[:, :3, 3]
    return _SHFn.apply(
        means, dc if dc.dim() == 3 else dc[None], rest if rest.dim() == 4 else rest[None], centres, degree
    )
