"""Sparse pure-torch Gaussian rasterizer with gsplat 1.4.0's ``rasterization`` interface.

gsplat's only CPU-capable rasterizer is the private ``_torch_impl._rasterize_to_pixels``, which
needs its CUDA ``rasterize_to_indices_in_range`` kernel and nerfacc; its ``_isect_tiles`` is a
Python loop per Gaussian. So this module implements compositing itself, vectorised in torch, for
any device (CPU or CUDA) and float32/float64.

Conventions (gsplat's): OpenCV cameras (world-to-camera ``viewmats``, +z forward), pixel units,
pixel ``(x, y)`` centred at ``(x + 0.5, y + 0.5)``; colours are linear, composited front to back
with ``alpha = min(0.999, opacity * exp(-sigma))``, pairs with ``sigma < 0`` or ``alpha < 1/255``
skipped, and a pixel stops *before* the Gaussian that would bring its transmittance to
``<= 1e-4``. Outputs are not clamped. A Gaussian touches only the pixels of its ``mean +- radius``
box (:func:`~naka_gs_plugin.model.projection.pixel_bounds`); gsplat evaluates every Gaussian of a
16x16 tile, so it can additionally pick up faint pairs (``alpha < 0.0111 * opacity``) just
outside that box.

How the sparse path works: the visible Gaussians, sorted by depth, are expanded into
(Gaussian, row) items covering the rows of their ``alpha >= 1/255`` ellipse, each with the column
span of the ellipse on that row (a slightly lenient bound, the exact test is applied per pair).
Items are grouped into bands of rows holding at most ``max_pairs_per_chunk`` pairs. Per band the
pairs are generated, stable-sorted by pixel (keeping depth order), and composited with a segmented
float64 cumulative sum of ``log(1 - alpha)``. Only the contributing pairs (their Gaussian, pixel
and transmittance: 12 bytes each in float32) are kept for the backward pass, which re-walks the
same bands with a hand-written gradient (including gsplat's per-pair ``absgrad``), so the other
temporaries are bounded by the band size, never pixels x Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Callable, Dict, List, Literal, Optional, Tuple

import torch
from jaxtyping import Float, Int
from torch import Tensor

from naka_gs_plugin.model.projection import Projection, pixel_bounds, project_gaussians, sh_colors

ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
TRANSMITTANCE_MIN = 1e-4
LOG_TRANSMITTANCE_MIN = math.log(TRANSMITTANCE_MIN)
TILE_SIZE = 16
"""Reported in ``meta`` for gsplat compatibility; this rasterizer does not use tiles."""

DEFAULT_MAX_PAIRS_PER_CHUNK = 1 << 17
"""Gaussian-pixel pairs per band (~100 bytes of temporaries each). Small bands keep the working
set in cache and let the allocator reuse memory; larger bands only save Python overhead."""

_ENUM_SLACK = 1e-3
"""Relative slack on the ``alpha >= 1/255`` ellipse used to enumerate pairs, so that rounding adds
candidates (rejected by the exact per-pair test) instead of dropping valid ones. The bound is
computed in float64; only a float32 sigma with extreme cancellation (anisotropy ~1e4) could
still differ from it, for pixels whose alpha is within rounding of 1/255."""

RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
Compositor = Callable[..., Tuple[Tensor, Tensor]]
"""``(means2d, conics, colors, opacities, depths, radii, width, height, backgrounds)`` ->
``(render_colors [C,H,W,D], render_alphas [C,H,W,1])``, all tensors per camera ``[C, N, ...]``."""


@dataclass
class _Band:
    item_start: int
    item_end: int
    row_start: int
    row_end: int
    n_pairs: int


@dataclass
class _PairPlan:
    """Row items of the visible Gaussians, sorted by (global row, depth), and their bands."""

    entry: Tensor  # [R] int64 flat (camera, Gaussian) index
    pix_base: Tensor  # [R] int64 global pixel id of the item's first column
    n_cols: Tensor  # [R] int64 columns of the item (>= 1)
    dx0: Tensor  # [R] mean.x - (first column + 0.5)
    dy: Tensor  # [R] mean.y - (row + 0.5)
    bands: List[_Band]


@torch.no_grad()
def _plan_pairs(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    max_pairs_per_chunk: int,
) -> _PairPlan:
    device = means2d.device
    n_cams, n = radii.shape
    flat_opac = opacities.reshape(-1)
    entries = torch.nonzero((radii.reshape(-1) > 0) & (flat_opac >= ALPHA_MIN)).squeeze(1)
    entries = entries.index_select(0, torch.argsort(depths.reshape(-1).index_select(0, entries), stable=True))

    box = pixel_bounds(means2d, radii, width, height).reshape(-1, 4).index_select(0, entries)
    mx, my = means2d.reshape(-1, 2).index_select(0, entries).double().unbind(-1)
    ca, cb, cc = conics.reshape(-1, 3).index_select(0, entries).double().unbind(-1)
    # alpha >= 1/255  <=>  sigma <= log(255 * opacity), sigma = 0.5 d^T conic d: an ellipse.
    level = torch.log(255.0 * flat_opac.index_select(0, entries).double())
    level = level * (1.0 + _ENUM_SLACK) + _ENUM_SLACK
    det_con = ca * cc - cb * cb
    half_h = torch.nan_to_num(torch.sqrt(2.0 * level * ca / det_con), nan=math.inf)
    y_lo = torch.maximum(torch.ceil(my - half_h - 0.5), box[:, 2].double())
    y_hi = torch.minimum(torch.floor(my + half_h - 0.5), box[:, 3].double())
    n_rows = (y_hi - y_lo + 1).clamp(min=0).long()

    # (Gaussian, row) items, Gaussian-major in depth order, with the ellipse's columns on the row.
    pos = torch.repeat_interleave(torch.arange(len(entries), device=device), n_rows)
    per_entry = torch.stack(
        [mx, my, ca, cb, cc, level, det_con, box[:, 0].double(), box[:, 1].double(), y_lo], dim=1
    ).index_select(0, pos)
    mx, my, a, b, c, level, det_con, box_x_lo, box_x_hi, y_lo = per_entry.unbind(-1)
    first_row_item = (torch.cumsum(n_rows, 0) - n_rows).index_select(0, pos)
    y = y_lo + (torch.arange(len(pos), device=device) - first_row_item).double()
    dy = my - (y + 0.5)
    disc = 2.0 * a * level - dy * dy * det_con
    root = torch.sqrt(disc.clamp(min=0.0))
    t_lo = torch.nan_to_num((-b * dy - root) / a, nan=-math.inf)
    t_hi = torch.nan_to_num((-b * dy + root) / a, nan=math.inf)
    x_lo = torch.maximum(torch.ceil(mx - t_hi - 0.5), box_x_lo)
    x_hi = torch.minimum(torch.floor(mx - t_lo - 0.5), box_x_hi)
    n_cols = torch.where(disc >= 0, x_hi - x_lo + 1, torch.zeros_like(x_hi)).clamp(min=0)

    entry = entries.index_select(0, pos)
    global_row = torch.div(entry, n, rounding_mode="floor") * height + y.long()
    keep = torch.nonzero(n_cols > 0).squeeze(1)
    keep = keep.index_select(0, torch.argsort(global_row.index_select(0, keep), stable=True))
    entry, global_row = entry.index_select(0, keep), global_row.index_select(0, keep)
    x_lo, n_cols = x_lo.index_select(0, keep), n_cols.index_select(0, keep).long()
    dx0 = mx.index_select(0, keep) - (x_lo + 0.5)
    dy = dy.index_select(0, keep)

    n_global_rows = n_cams * height
    row_pairs = torch.zeros(n_global_rows, dtype=torch.int64, device=device)
    row_pairs.index_add_(0, global_row, n_cols)
    row_first_item = torch.searchsorted(global_row, torch.arange(n_global_rows + 1, device=device)).tolist()
    bands: List[_Band] = []
    start, acc = 0, 0
    for row, count in enumerate(row_pairs.tolist()):
        if acc > 0 and acc + count > max_pairs_per_chunk:
            bands.append(_Band(row_first_item[start], row_first_item[row], start, row, acc))
            start, acc = row, 0
        acc += count
    if acc > 0:
        bands.append(_Band(row_first_item[start], row_first_item[n_global_rows], start, n_global_rows, acc))
    return _PairPlan(
        entry=entry,
        pix_base=global_row * width + x_lo.long(),
        n_cols=n_cols,
        dx0=dx0.to(means2d.dtype),
        dy=dy.to(means2d.dtype),
        bands=bands,
    )


def _sigma(dx: Tensor, dy: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Gaussian exponent ``0.5 (a dx^2 + c dy^2) + b dx dy`` for conic ``(a, b, c)``."""
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


class _SparseComposite(torch.autograd.Function):
    """Front-to-back compositing over the planned pairs; backward recomputes per band."""

    @staticmethod
    def forward(
        ctx,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        backgrounds: Optional[Tensor],
        plan: _PairPlan,
        width: int,
        height: int,
        absgrad: bool,
    ) -> Tuple[Tensor, Tensor]:
        n_cams, n, dim = colors.shape
        dtype, device = colors.dtype, colors.device
        n_pix = n_cams * height * width
        geom = torch.cat([conics.reshape(-1, 3), opacities.reshape(-1, 1)], dim=1)  # [E, 4]: a, b, c, opacity
        flat_colors = colors.reshape(-1, dim)
        out = torch.zeros(n_pix, dim, dtype=dtype, device=device)
        log_t_final = torch.zeros(n_pix, dtype=torch.float64, device=device)
        kept_entry, kept_pix, kept_t, pair_bands = [], [], [], []
        n_kept = 0
        for band in plan.bands:
            items = slice(band.item_start, band.item_end)
            n_cols = plan.n_cols[items]
            pix0 = band.row_start * width
            n_band_pix = (band.row_end - band.row_start) * width
            entry_items = plan.entry[items]
            first = torch.cumsum(n_cols, 0) - n_cols
            # Per item: (dx0, dy, a, b, c, opacity) and (entry, key of column 0 minus first, first).
            ftab = torch.cat([plan.dx0[items, None], plan.dy[items, None], geom.index_select(0, entry_items)], 1)
            itab = torch.stack([entry_items, plan.pix_base[items] - pix0 - first, first], 1)
            item = torch.repeat_interleave(torch.arange(len(n_cols), device=device), n_cols, output_size=band.n_pairs)
            f = ftab.index_select(0, item)
            it = itab.index_select(0, item)
            arange = torch.arange(band.n_pairs, device=device)
            key = (it[:, 1] + arange).to(torch.int32)
            dx = f[:, 0] - (arange - it[:, 2]).to(dtype)
            sigma = _sigma(dx, f[:, 1], f[:, 2], f[:, 3], f[:, 4])
            alpha = torch.clamp_max(f[:, 5] * torch.exp(-sigma), ALPHA_MAX)
            alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))

            key, perm = torch.sort(key, stable=True)
            alpha = alpha.index_select(0, perm)
            entry = it[:, 0].index_select(0, perm)
            log_1m = torch.log1p(-alpha.double())
            csum = torch.cumsum(log_1m, 0)
            counts = torch.bincount(key, minlength=n_band_pix)
            before = torch.cat([csum.new_zeros(1), csum]).index_select(0, torch.cumsum(counts, 0) - counts)
            log_t_incl = csum - before.index_select(0, key)
            contrib = torch.nonzero((alpha > 0) & (log_t_incl > LOG_TRANSMITTANCE_MIN)).squeeze(1)
            if len(contrib) == 0:  # only lenient-bound candidates below 1/255 in this band
                continue

            entry, key = entry.index_select(0, contrib), key.index_select(0, contrib)
            alpha, log_1m = alpha.index_select(0, contrib), log_1m.index_select(0, contrib)
            log_t_incl = log_t_incl.index_select(0, contrib)
            trans = torch.exp(log_t_incl - log_1m).to(dtype)
            weight = alpha * trans
            # Pairs are grouped by pixel: sum per segment; T_final is T after a pixel's last pair.
            counts = torch.bincount(key, minlength=n_band_pix)
            out[pix0 : pix0 + n_band_pix] = torch.segment_reduce(
                weight[:, None] * flat_colors.index_select(0, entry), "sum", lengths=counts, axis=0
            )
            last = (torch.cumsum(counts, 0) - 1).clamp(min=0)
            log_t_final[pix0 : pix0 + n_band_pix] = torch.where(counts > 0, log_t_incl.index_select(0, last), 0.0)

            kept_entry.append(entry.to(torch.int32))
            kept_pix.append(key + pix0)
            kept_t.append(trans)
            pair_bands.append((n_kept, n_kept + len(entry), band.row_start, band.row_end))
            n_kept += len(entry)

        t_final = torch.exp(log_t_final).to(dtype)
        if backgrounds is not None:
            out = out + (t_final.reshape(n_cams, -1, 1) * backgrounds[:, None, :]).reshape(n_pix, dim)
        ctx.save_for_backward(
            means2d,
            conics,
            opacities,
            colors,
            backgrounds,
            t_final,
            torch.cat(kept_entry) if kept_entry else torch.zeros(0, dtype=torch.int32, device=device),
            torch.cat(kept_pix) if kept_pix else torch.zeros(0, dtype=torch.int32, device=device),
            torch.cat(kept_t) if kept_t else torch.zeros(0, dtype=dtype, device=device),
        )
        ctx.pair_bands = pair_bands
        ctx.image_size = (width, height)
        ctx.absgrad = absgrad
        return (
            out.reshape(n_cams, height, width, dim),
            (1.0 - t_final).reshape(n_cams, height, width, 1),
        )

    @staticmethod
    def backward(ctx, grad_colors: Tensor, grad_alphas: Tensor):
        (means2d, conics, opacities, colors, backgrounds, t_final, p_entry, p_pix, p_trans) = ctx.saved_tensors
        width, height = ctx.image_size
        n_cams, n, dim = colors.shape
        dtype, device = colors.dtype, colors.device
        grad_colors = grad_colors.reshape(-1, dim)
        grad_bg_dot = 0.0
        if backgrounds is not None:
            grad_bg_dot = (grad_colors.reshape(n_cams, -1, dim) * backgrounds[:, None, :]).sum(-1)
            grad_bg_dot = grad_bg_dot.reshape(-1)
        # Per pixel: upstream colour gradient and Q = T_final * (G . background - G_alpha).
        q = t_final * (grad_bg_dot - grad_alphas.reshape(-1))
        grad_pix = torch.cat([grad_colors, q[:, None]], dim=1)

        feats = torch.cat(
            [
                means2d.reshape(-1, 2),
                conics.reshape(-1, 3),
                opacities.reshape(-1, 1),
                colors.reshape(-1, dim),
            ],
            dim=1,
        )  # [E, 6 + D]
        # Per entry: d means2d (2), |d means2d| (2), d conics (3), d opacity (1), d colors (D).
        acc = torch.zeros(feats.shape[0], 8 + dim, dtype=dtype, device=device)
        for p0, p1, row0, row1 in ctx.pair_bands:
            if p0 == p1:
                continue
            pix0 = row0 * width
            n_band_pix = (row1 - row0) * width
            entry = p_entry[p0:p1].long()
            key = p_pix[p0:p1].long() - pix0
            trans = p_trans[p0:p1]
            f = feats.index_select(0, entry)
            px = torch.remainder(key, width).to(dtype) + 0.5
            py = torch.remainder(torch.div(key, width, rounding_mode="floor") + row0, height)
            dx = f[:, 0] - px
            dy = f[:, 1] - (py.to(dtype) + 0.5)
            a, b, c, opac = f[:, 2], f[:, 3], f[:, 4], f[:, 5]
            vis = torch.exp(-_sigma(dx, dy, a, b, c))
            raw = opac * vis
            alpha = torch.clamp_max(raw, ALPHA_MAX)
            weight = alpha * trans

            g = grad_pix[pix0 : pix0 + n_band_pix].index_select(0, key)
            g_col = g[:, :dim]
            gc = (g_col * f[:, 6:]).sum(1)
            csum = torch.cumsum((weight * gc).double(), 0)
            counts = torch.bincount(key, minlength=n_band_pix)
            seg_end = torch.cat([csum.new_zeros(1), csum]).index_select(0, torch.cumsum(counts, 0))
            behind = (seg_end.index_select(0, key) - csum).to(dtype)  # sum over later pairs of w_j (G . c_j)
            grad_alpha = trans * gc - (behind + g[:, dim]) / (1.0 - alpha)

            unclamped = raw <= ALPHA_MAX
            zero = torch.zeros_like(raw)
            grad_sigma = torch.where(unclamped, -raw * grad_alpha, zero)
            grad_opac = torch.where(unclamped, vis * grad_alpha, zero)
            gmx = grad_sigma * (a * dx + b * dy)
            gmy = grad_sigma * (b * dx + c * dy)
            per_pair = torch.cat(
                [
                    torch.stack(
                        [
                            gmx,
                            gmy,
                            gmx.abs(),
                            gmy.abs(),
                            0.5 * grad_sigma * dx * dx,
                            grad_sigma * dx * dy,
                            0.5 * grad_sigma * dy * dy,
                            grad_opac,
                        ],
                        dim=1,
                    ),
                    weight[:, None] * g_col,
                ],
                dim=1,
            )
            acc.index_add_(0, entry, per_pair)

        if ctx.absgrad:
            means2d.absgrad = acc[:, 2:4].reshape(n_cams, n, 2)
        grad_bg = None
        if backgrounds is not None:
            grad_bg = (grad_colors.reshape(n_cams, -1, dim) * t_final.reshape(n_cams, -1, 1)).sum(1)
        return (
            acc[:, 0:2].reshape(n_cams, n, 2),
            acc[:, 4:7].reshape(n_cams, n, 3),
            acc[:, 7].reshape(n_cams, n),
            acc[:, 8:].reshape(n_cams, n, dim),
            grad_bg,
            None,
            None,
            None,
            None,
        )


def rasterize_to_pixels_sparse(
    means2d: Float[Tensor, "C N 2"],
    conics: Float[Tensor, "C N 3"],
    colors: Float[Tensor, "C N D"],
    opacities: Float[Tensor, "C N"],
    depths: Float[Tensor, "C N"],
    radii: Int[Tensor, "C N"],
    width: int,
    height: int,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    absgrad: bool = False,
    max_pairs_per_chunk: int = DEFAULT_MAX_PAIRS_PER_CHUNK,
) -> Tuple[Float[Tensor, "C H W D"], Float[Tensor, "C H W 1"]]:
    """Composite screen-space Gaussians front to back (gsplat ``rasterize_to_pixels`` semantics).

    Differentiable w.r.t. means2d, conics, colors, opacities and backgrounds. With ``absgrad``, the
    backward pass sets ``means2d.absgrad`` [C, N, 2]: the sum over pixels of the absolute value of
    each pixel's gradient w.r.t. the Gaussian's 2D mean (gsplat's definition).
    """
    plan = _plan_pairs(
        means2d.detach(),
        conics.detach(),
        opacities.detach(),
        depths.detach(),
        radii,
        width,
        height,
        max_pairs_per_chunk,
    )
    return _SparseComposite.apply(means2d, conics, opacities, colors, backgrounds, plan, width, height, absgrad)


def _shade_torch(means: Tensor, colors: Tensor, viewmats: Tensor, degree: int) -> Tensor:
    """:func:`sh_colors` on [N, K, 3] (shared by the cameras) or [C, N, K, 3] coefficients, or the pair
    ``(features_dc [N, 3], features_rest [N, K - 1, 3])``."""
    if isinstance(colors, tuple):
        colors = torch.cat((colors[0][:, None, :], colors[1]), dim=1)
    coeffs = colors.expand(viewmats.shape[0], *colors.shape) if colors.dim() == 3 else colors
    return sh_colors(means, coeffs, viewmats, degree)


def rasterization_with_compositor(
    compositor: Compositor,
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
    project: Callable[..., Projection] = project_gaussians,
    shade: Optional[Callable[[Tensor, Tensor, Tensor, int], Tensor]] = None,
) -> Tuple[Float[Tensor, "C H W X"], Float[Tensor, "C H W 1"], Dict]:
    """gsplat 1.4.0 ``rasterization`` (unpacked, pinhole) with pluggable steps: ``compositor``, and
    ``project`` / ``shade`` (``project_gaussians``'s and ``shade(means, colors, viewmats, sh_degree)``
    interfaces, ``colors`` as given: [N, K, 3] or [C, N, K, 3], or with ``sh_degree`` splatfacto's pair
    ``(features_dc [N, 3], features_rest [N, K - 1, 3])``; default the torch reference)."""
    shade = shade or _shade_torch
    n = means.shape[0]
    n_cams = viewmats.shape[0]
    if render_mode not in ("RGB", "D", "ED", "RGB+D", "RGB+ED"):
        raise ValueError(f"unknown render_mode {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"unknown rasterize_mode {rasterize_mode!r}")
    if means.shape != (n, 3) or quats.shape != (n, 4) or scales.shape != (n, 3):
        raise ValueError(f"bad shapes: means {means.shape}, quats {quats.shape}, scales {scales.shape}")
    if opacities.shape != (n,) or viewmats.shape != (n_cams, 4, 4) or Ks.shape != (n_cams, 3, 3):
        raise ValueError(f"bad shapes: opacities {opacities.shape}, viewmats {viewmats.shape}, Ks {Ks.shape}")

    proj = project(
        means,
        quats,
        scales,
        viewmats,
        Ks,
        width,
        height,
        eps2d=eps2d,
        near_plane=near_plane,
        far_plane=far_plane,
        calc_compensations=rasterize_mode == "antialiased",
    )
    opacities = opacities[None, :].expand(n_cams, n)
    if proj.compensations is not None:
        opacities = opacities * proj.compensations

    if sh_degree is None:
        if not (colors.dim() == 2 and colors.shape[0] == n) and colors.shape[:2] != (n_cams, n):
            raise ValueError(f"colors must be [N, D] or [C, N, D], got {tuple(colors.shape)}")
        feats = colors.expand(n_cams, n, colors.shape[-1]) if colors.dim() == 2 else colors
    else:
        if isinstance(colors, tuple):  # splatfacto's (features_dc, features_rest), for a shade that takes them
            if len(colors) != 2 or colors[0].shape != (n, 3) or colors[1].dim() != 3 or colors[1].shape[0] != n:
                raise ValueError(
                    f"SH colors as a pair must be ([N, 3], [N, K-1, 3]), got {[tuple(c.shape) for c in colors]}"
                )
        elif not (colors.dim() == 3 and colors.shape[0] == n) and colors.shape[:2] != (n_cams, n):
            raise ValueError(f"SH colors must be [N, K, 3] or [C, N, K, 3], got {tuple(colors.shape)}")
        feats = shade(means, colors, viewmats, sh_degree)

    if render_mode in ("RGB+D", "RGB+ED"):
        feats = torch.cat([feats, proj.depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cams, 1)], dim=-1)
    elif render_mode in ("D", "ED"):
        feats = proj.depths[..., None]
        if backgrounds is not None:
            backgrounds = backgrounds.new_zeros(n_cams, 1)

    render_colors, render_alphas = compositor(
        proj.means2d,
        proj.conics,
        feats,
        opacities,
        proj.depths,
        proj.radii,
        width,
        height,
        backgrounds,
    )
    if render_mode in ("ED", "RGB+ED"):
        render_colors = torch.cat(
            [render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)],
            dim=-1,
        )
    meta = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": proj.radii,
        "means2d": proj.means2d,
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": opacities,
        "width": width,
        "height": height,
        "n_cameras": n_cams,
        "tile_size": TILE_SIZE,
    }
    return render_colors, render_alphas, meta


def rasterization(
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
    absgrad: bool = False,
    eps2d: float = 0.3,
    max_pairs_per_chunk: int = DEFAULT_MAX_PAIRS_PER_CHUNK,
) -> Tuple[Float[Tensor, "C H W X"], Float[Tensor, "C H W 1"], Dict]:
    """Render Gaussians like ``gsplat.rendering.rasterization`` 1.4.0 (``packed=False``, pinhole).

    ``means`` [N,3] world, ``quats`` [N,4] wxyz (any norm), ``scales`` [N,3] (exp'ed),
    ``opacities`` [N] (sigmoid'ed). ``colors`` are SH coefficients [N,K,3] or [C,N,K,3] when
    ``sh_degree`` is set (colour = max(SH + 0.5, 0)), else post-activation features [N,D] or
    [C,N,D]. ``viewmats`` [C,4,4] world-to-camera (OpenCV), ``Ks`` [C,3,3] px. Returns
    ``render_colors`` [C,H,W,X] (X = D, 1 for "D"/"ED", D+1 for "RGB+D"/"RGB+ED", depth last, "ED"
    divided by max(alpha, 1e-10)), ``render_alphas`` [C,H,W,1] and ``meta`` with ``radii`` [C,N]
    int32, ``means2d`` [C,N,2] (non-leaf; ``retain_grad()`` gives dL/dmeans2d, and with ``absgrad``
    the backward sets ``meta["means2d"].absgrad``), ``depths``, ``conics``, ``opacities``, ``width``,
    ``height``, ``n_cameras``, ``gaussian_ids=None``, ``camera_ids=None``, ``tile_size``.
    Colours are linear and not clamped. Works on CPU and CUDA tensors, float32 or float64.
    """
    compositor = partial(rasterize_to_pixels_sparse, absgrad=absgrad, max_pairs_per_chunk=max_pairs_per_chunk)
    return rasterization_with_compositor(
        compositor,
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
