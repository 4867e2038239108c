"""The sparse pure-torch rasterizer against the dense reference, gsplat's torch helpers and autograd."""

from __future__ import annotations

import math

import pytest
import torch
from gsplat.cuda._torch_impl import (
    _fully_fused_projection,
    _quat_scale_to_covar_preci,
    _spherical_harmonics,
)

from benchmarks.cuda_parity import make_scene
from naka_gs_plugin.model.projection import (
    pixel_bounds,
    project_gaussians,
    quat_scale_to_covar,
    spherical_harmonics,
)
from naka_gs_plugin.model.rasterize import (
    ALPHA_MIN,
    TRANSMITTANCE_MIN,
    rasterization,
    rasterize_to_pixels_sparse,
)
from naka_gs_plugin.model.rasterize_dense import rasterization_dense, rasterize_to_pixels_dense

F64 = torch.float64


def render_both(scene, **kwargs):
    sparse = rasterization(**scene, **kwargs)
    kwargs.pop("max_pairs_per_chunk", None)
    dense = rasterization_dense(**scene, **kwargs)
    return sparse, dense


@pytest.mark.parametrize("render_mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
@pytest.mark.parametrize("with_background", [False, True])
def test_sparse_matches_dense_render_modes(render_mode, with_background):
    scene = make_scene(150, 40, 30, n_cams=2, scale=0.08)
    bg = torch.rand(2, 3, dtype=F64) if with_background else None
    (sc, sa, smeta), (dc, da, _) = render_both(scene, backgrounds=bg, render_mode=render_mode, max_pairs_per_chunk=700)
    assert sc.shape == dc.shape == (2, 30, 40, {"RGB": 3, "D": 1, "ED": 1}.get(render_mode, 4))
    assert sa.shape == (2, 30, 40, 1)
    assert 0.2 < float(sa.mean()) < 0.95  # overlapping, partly covered images
    assert torch.allclose(sc, dc, rtol=0, atol=1e-6)
    assert torch.allclose(sa, da, rtol=0, atol=1e-6)
    if with_background and render_mode == "RGB":  # uncovered pixels show the background
        empty = sa[..., 0] < 1e-12
        assert empty.any()
        assert torch.allclose(sc[empty], bg[:, None, None, :].expand_as(sc)[empty], atol=1e-12)


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_sparse_matches_dense_sh(sh_degree):
    scene = make_scene(120, 36, 28, sh_degree=sh_degree, seed=sh_degree, scale=0.08)
    (sc, sa, _), (dc, da, _) = render_both(scene, render_mode="RGB+ED")
    assert torch.allclose(sc, dc, rtol=0, atol=1e-6)
    assert torch.allclose(sa, da, rtol=0, atol=1e-6)


def _stacked_scene(opacity, n=8, dtype=F64):
    """``n`` identical round Gaussians on the optical axis, one behind the other."""
    width = height = 9
    means = torch.zeros(n, 3, dtype=dtype)
    means[:, 2] = 2.0 + 0.1 * torch.arange(n, dtype=dtype)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(3), dtype=dtype)
    k = torch.tensor([[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]], dtype=dtype)
    return dict(
        means=means,
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dtype).repeat(n, 1),
        scales=torch.full((n, 3), 0.2, dtype=dtype),
        opacities=torch.full((n,), opacity, dtype=dtype),
        colors=colors,
        viewmats=torch.eye(4, dtype=dtype)[None],
        Ks=k[None],
        width=width,
        height=height,
    )


def test_early_stop_is_exclusive_and_matches_dense():
    # The centre pixel sits on every mean: alpha = 0.95 each. T after k Gaussians is 0.05^k:
    # 0.05, 2.5e-3, 1.25e-4, 6.25e-6 <= 1e-4, so exactly the first three contribute.
    scene = _stacked_scene(opacity=0.95)
    (sc, sa, _), (dc, da, _) = render_both(scene)
    colors = scene["colors"]
    alpha = 0.95
    expected = sum(colors[k] * alpha * (1 - alpha) ** k for k in range(3))
    without_stop = sum(colors[k] * alpha * (1 - alpha) ** k for k in range(8))
    assert (1 - alpha) ** 8 < TRANSMITTANCE_MIN  # the stop matters at this pixel ...
    assert not torch.allclose(expected, without_stop, atol=1e-7)  # ... and changes the colour
    assert torch.allclose(sc[0, 4, 4], expected, atol=1e-12)
    assert float(1 - sa[0, 4, 4, 0]) == pytest.approx((1 - alpha) ** 3, rel=1e-9)
    assert torch.allclose(sc, dc, atol=1e-6) and torch.allclose(sa, da, atol=1e-6)


def test_chunked_equals_single_chunk():
    scene = make_scene(200, 48, 32, n_cams=2, sh_degree=1, scale=0.08)
    grads = []
    outputs = []
    for chunk in (1, 300, 10**9):  # one row per band (and beyond the budget), some bands, one band
        inputs = {k: v.clone().requires_grad_() for k, v in scene.items() if k in ("means", "colors")}
        colors, alphas, meta = rasterization(
            **{**scene, **inputs}, render_mode="RGB+ED", absgrad=True, max_pairs_per_chunk=chunk
        )
        (colors.square().sum() + alphas.sum()).backward()
        outputs.append((colors, alphas))
        grads.append((inputs["means"].grad, inputs["colors"].grad, meta["means2d"].absgrad))
    for (c, a), g in zip(outputs[:2], grads[:2]):
        assert torch.allclose(c, outputs[2][0], atol=1e-9) and torch.allclose(a, outputs[2][1], atol=1e-9)
        for x, y in zip(g, grads[2]):
            assert torch.allclose(x, y, atol=1e-8)


def test_gradients_match_dense():
    scene = make_scene(120, 32, 24, n_cams=2, sh_degree=2, scale=0.08)
    bg = torch.rand(2, 3, dtype=F64)
    weights = torch.rand(2, 24, 32, 4, dtype=F64)
    names = ("means", "quats", "scales", "opacities", "colors", "viewmats")
    grads = []
    for fn in (rasterization, rasterization_dense):
        inputs = {k: scene[k].clone().requires_grad_() for k in names}
        background = bg.clone().requires_grad_()
        colors, alphas, _ = fn(
            **{**scene, **inputs}, backgrounds=background, render_mode="RGB+ED", rasterize_mode="antialiased"
        )
        ((colors * weights).sum() + alphas.square().sum()).backward()
        grads.append([inputs[k].grad for k in names] + [background.grad])
    for sparse, dense in zip(*grads):
        assert torch.allclose(sparse, dense, rtol=1e-9, atol=1e-9)


def _tiny_gradcheck_scene():
    """Three Gaussians on a 10x8 image whose pairs stay clear of every discontinuity."""
    scene = make_scene(3, 10, 8, sh_degree=1, seed=5, scale=0.12)
    scene["means"][:, :2] *= 0.5  # keep them well inside the image
    scene["opacities"] = torch.tensor([0.7, 0.55, 0.9], dtype=F64)
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], 10, 8)
    # The radius (ceil) must not be near an integer, nor a box edge near a pixel centre, ...
    assert (proj.radii > 0).all()
    cov = torch.linalg.inv(
        torch.stack([proj.conics[..., 0], proj.conics[..., 1], proj.conics[..., 1], proj.conics[..., 2]], -1).reshape(
            1, 3, 2, 2
        )
    )
    half_trace = 0.5 * (cov[..., 0, 0] + cov[..., 1, 1])
    lam = half_trace + torch.sqrt(torch.clamp(half_trace**2 - torch.linalg.det(cov), min=0.01))
    three_sigma = 3 * torch.sqrt(lam)
    assert ((three_sigma - three_sigma.floor()) > 1e-3).all()
    edges = torch.cat([proj.means2d - proj.radii[..., None], proj.means2d + proj.radii[..., None]], -1) - 0.5
    assert ((edges - edges.round()).abs() > 1e-3).all()
    # ... and no pair's alpha near 1/255 or 0.999, no transmittance near 1e-4.
    ys, xs = torch.meshgrid(torch.arange(8, dtype=F64), torch.arange(10, dtype=F64), indexing="ij")
    d = proj.means2d[0, :, None, None, :] - torch.stack([xs, ys], -1) - 0.5
    c = proj.conics[0, :, None, None, :]
    sigma = 0.5 * (c[..., 0] * d[..., 0] ** 2 + c[..., 2] * d[..., 1] ** 2) + c[..., 1] * d[..., 0] * d[..., 1]
    raw = scene["opacities"][:, None, None] * torch.exp(-sigma)
    assert ((raw - ALPHA_MIN).abs() > 1e-4).all() and (raw < 0.99).all()
    _, alphas, _ = rasterization_dense(**scene)
    assert float(1 - alphas.max()) > 10 * TRANSMITTANCE_MIN
    return scene


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_gradcheck(rasterize_mode):
    scene = _tiny_gradcheck_scene()
    names = ("means", "quats", "scales", "opacities", "colors")

    def render(*tensors):
        colors, alphas, _ = rasterization(
            **{**scene, **dict(zip(names, tensors))}, render_mode="RGB+ED", rasterize_mode=rasterize_mode
        )
        return colors, alphas

    inputs = tuple(scene[k].clone().requires_grad_() for k in names)
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def _per_pixel_absgrad(means2d, conics, colors, opacities, depths, radii, width, height, weights):
    """Reference: sum over pixels of |d(pixel's loss term)/d means2d|, one backward per pixel."""
    total = torch.zeros_like(means2d)
    for y in range(height):
        for x in range(width):
            m2d = means2d.clone().requires_grad_()
            out, alpha = rasterize_to_pixels_dense(m2d, conics, colors, opacities, depths, radii, width, height)
            term = (torch.cat([out, alpha], -1)[:, y, x] * weights[:, y, x]).sum()
            (grad,) = torch.autograd.grad(term, m2d)
            total += grad.abs()
    return total


def test_absgrad_matches_per_pixel_reference():
    scene = make_scene(40, 14, 10, scale=0.1, seed=2)
    means = scene["means"].clone().requires_grad_()
    colors, alphas, meta = rasterization(**{**scene, "means": means}, absgrad=True, max_pairs_per_chunk=50)
    meta["means2d"].retain_grad()
    weights = torch.randn(1, 10, 14, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    (torch.cat([colors, alphas], -1) * weights).sum().backward()

    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], 14, 10)
    feats = scene["colors"][None]
    opac = scene["opacities"][None]
    expected = _per_pixel_absgrad(proj.means2d, proj.conics, feats, opac, proj.depths, proj.radii, 14, 10, weights)
    absgrad = meta["means2d"].absgrad
    assert absgrad.shape == (1, 40, 2)
    assert torch.allclose(absgrad, expected, rtol=1e-9, atol=1e-12)
    assert (absgrad >= meta["means2d"].grad.abs() - 1e-12).all()
    assert float(absgrad.sum()) > 1.0


def test_absgrad_differs_from_abs_grad_when_pixels_cancel():
    # One round Gaussian centred on a 10x10 image; loss = total alpha. Pixels left and right of
    # the centre pull its x mean in opposite directions, so the gradient cancels, absgrad does not.
    scene = _stacked_scene(opacity=0.8, n=1)
    scene.update(width=10, height=10, Ks=torch.tensor([[[10.0, 0, 5.0], [0, 10.0, 5.0], [0, 0, 1]]], dtype=F64))
    scene["means"].requires_grad_()
    _, alphas, meta = rasterization(**scene, absgrad=True)
    meta["means2d"].retain_grad()
    alphas.sum().backward()
    grad, absgrad = meta["means2d"].grad[0, 0], meta["means2d"].absgrad[0, 0]
    assert grad.abs().max() < 1e-10
    assert (absgrad > 0.1).all()


def test_projection_matches_gsplat_torch_impl():
    gen = torch.Generator().manual_seed(7)
    n, width, height = 3000, 120, 90
    means = torch.randn(n, 3, generator=gen, dtype=F64) * torch.tensor([3.0, 2.0, 2.0], dtype=F64)
    means[:, 2] += 3.0  # some behind the camera, some far off-screen (Jacobian clamping)
    quats = torch.randn(n, 4, generator=gen, dtype=F64)
    scales = torch.exp(torch.randn(n, 3, generator=gen, dtype=F64) - 2.5)
    viewmats = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    viewmats[1, :3, :3] = torch.linalg.matrix_exp(
        torch.tensor([[0, -0.2, 0.1], [0.2, 0, -0.3], [-0.1, 0.3, 0]], dtype=F64)
    )
    viewmats[1, :3, 3] = torch.tensor([0.4, -0.3, 0.5], dtype=F64)
    ks = torch.tensor([[[100.0, 0, 60], [0, 110, 45], [0, 0, 1]], [[90.0, 0, 50], [0, 95, 40], [0, 0, 1]]], dtype=F64)

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    assert torch.allclose(quat_scale_to_covar(quats, scales), covars, atol=1e-14)

    radii, means2d, depths, conics, comps = _fully_fused_projection(
        means, covars, viewmats, ks, width, height, calc_compensations=True
    )
    ours = project_gaussians(means, quats, scales, viewmats, ks, width, height, calc_compensations=True)
    assert torch.equal(ours.radii, radii)
    visible = radii > 0
    assert 0.2 < visible.double().mean() < 0.8  # both culled and kept Gaussians are exercised
    for a, b in ((ours.means2d, means2d), (ours.depths, depths), (ours.conics, conics), (ours.compensations, comps)):
        assert torch.allclose(a[visible], b[visible], rtol=1e-10, atol=1e-10)
    for t in (ours.means2d, ours.depths, ours.conics, ours.compensations):
        assert (t[~visible] == 0).all()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_match_gsplat(degree):
    gen = torch.Generator().manual_seed(degree)
    dirs = torch.randn(500, 3, generator=gen, dtype=F64) * 3.0  # unnormalised on purpose
    coeffs = torch.randn(500, 16, 3, generator=gen, dtype=F64)
    assert torch.allclose(
        spherical_harmonics(degree, dirs, coeffs), _spherical_harmonics(degree, dirs, coeffs), atol=1e-13
    )


def test_radius_formula():
    # An isotropic Gaussian on the optical axis: cov2d = (f s / z)^2 I, blurred by 0.3 px^2, so
    # b = (f s / z)^2 + 0.3, b^2 - det = 0 -> clamped to 0.01, lambda_max = b + 0.1.
    f, s, z = 50.0, 0.1, 2.0
    proj = project_gaussians(
        torch.tensor([[0.0, 0.0, z]], dtype=F64),
        torch.tensor([[2.0, 0.0, 0.0, 0.0]], dtype=F64),  # unnormalised identity rotation
        torch.full((1, 3), s, dtype=F64),
        torch.eye(4, dtype=F64)[None],
        torch.tensor([[[f, 0, 32.0], [0, f, 24.0], [0, 0, 1]]], dtype=F64),
        64,
        48,
    )
    b = (f * s / z) ** 2 + 0.3
    assert int(proj.radii) == math.ceil(3 * math.sqrt(b + 0.1)) == 8
    assert torch.allclose(proj.conics, torch.tensor([[[1 / b, 0.0, 1 / b]]], dtype=F64))
    assert torch.equal(pixel_bounds(proj.means2d, proj.radii, 64, 48), torch.tensor([[[24, 39, 16, 31]]]))


def test_culling_behind_far_and_outside():
    k = torch.tensor([[[20.0, 0, 10.0], [0, 20.0, 8.0], [0, 0, 1]]], dtype=F64)
    means = torch.tensor(
        [
            [0.0, 0.0, 2.0],  # visible
            [0.0, 0.0, -1.0],  # behind the camera
            [0.0, 0.0, 0.005],  # in front of the near plane
            [0.0, 0.0, 200.0],  # beyond far_plane=100
            [-2.3, 0.0, 2.0],  # box entirely left of the image: x + radius <= 0
            [0.0, 3.0, 2.0],  # box entirely below the image
            [-1.1, 0.0, 2.0],  # centre left of the image, box overlaps it: kept
        ],
        dtype=F64,
    )
    n = len(means)
    scene = dict(
        means=means.clone().requires_grad_(),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(n, 1),
        scales=torch.full((n, 3), 0.05, dtype=F64),
        opacities=torch.full((n,), 0.9, dtype=F64),
        colors=torch.rand(n, 3, dtype=F64),
        viewmats=torch.eye(4, dtype=F64)[None],
        Ks=k,
        width=20,
        height=16,
        far_plane=100.0,
    )
    colors, alphas, meta = rasterization(**scene)
    # f s / z = 0.5 px: b = 0.25 + 0.3, radius = ceil(3 sqrt(b + 0.1)) = 3.
    assert meta["radii"].tolist() == [[3, 0, 0, 0, 0, 0, 3]]
    assert float(meta["means2d"][0, 6, 0].detach()) < 0  # the kept one really is off-image
    (colors.sum() + alphas.sum()).backward()
    grad = scene["means"].grad
    assert torch.isfinite(grad).all()
    assert (grad[1:6] == 0).all() and (grad[[0, 6]].abs().sum(1) > 0).all()
    only_visible = {
        **scene,
        "means": means[[0, 6]],
        "quats": scene["quats"][:2],
        "scales": scene["scales"][:2],
        "opacities": scene["opacities"][:2],
        "colors": scene["colors"][[0, 6]],
    }
    colors2, alphas2, _ = rasterization(**only_visible)
    assert torch.allclose(colors, colors2, atol=1e-15) and torch.allclose(alphas, alphas2, atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_degenerate_inputs_are_finite(dtype, rasterize_mode):
    scene = make_scene(6, 24, 18, sh_degree=2, seed=4, dtype=dtype, scale=0.1)
    scene["scales"][0] = 1e-12  # collapsed
    scene["scales"][1] = 1e3  # huge: covers the whole image
    scene["quats"][2] = 0.0  # zero quaternion
    scene["means"][:2, :2] = 0.0  # the collapsed and the huge one in view
    logits = torch.tensor([30.0, 30.0, 30.0, -30.0, 0.0, 30.0], dtype=dtype)  # saturated opacities
    names = ("means", "quats", "scales", "colors")
    inputs = {k: scene[k].clone().requires_grad_() for k in names}
    logits.requires_grad_()
    colors, alphas, meta = rasterization(
        **{**scene, **inputs, "opacities": torch.sigmoid(logits)},
        render_mode="RGB+ED",
        rasterize_mode=rasterize_mode,
        absgrad=True,
    )
    assert (meta["radii"][0, [0, 1]] > 0).all()
    assert float(alphas.detach().min()) > 0.9  # the huge opaque Gaussian covers every pixel
    (colors.sum() + alphas.sum()).backward()
    for t in [colors, alphas, logits.grad, meta["means2d"].absgrad] + [inputs[k].grad for k in names]:
        assert torch.isfinite(t).all()


def test_float32_close_to_float64():
    scene = make_scene(300, 48, 36, sh_degree=3, scale=0.08)
    c64, a64, _ = rasterization(**scene, render_mode="RGB+ED")
    scene32 = {k: v.float() if torch.is_tensor(v) else v for k, v in scene.items()}
    c32, a32, meta = rasterization(**scene32, render_mode="RGB+ED")
    assert c32.dtype == a32.dtype == meta["means2d"].dtype == torch.float32
    assert (c32.double() - c64).abs().max() < 1e-4
    assert (a32.double() - a64).abs().max() < 1e-5


def test_meta_matches_gsplat_layout():
    scene = make_scene(50, 20, 16, n_cams=2, sh_degree=3)
    scene["means"].requires_grad_()
    colors, alphas, meta = rasterization(**scene, render_mode="RGB+ED")
    assert meta["radii"].dtype == torch.int32 and meta["radii"].shape == (2, 50)
    assert meta["means2d"].shape == (2, 50, 2) and not meta["means2d"].is_leaf
    assert meta["depths"].shape == meta["opacities"].shape == (2, 50)
    assert meta["conics"].shape == (2, 50, 3)
    assert (meta["width"], meta["height"], meta["n_cameras"], meta["tile_size"]) == (20, 16, 2, 16)
    assert meta["gaussian_ids"] is None and meta["camera_ids"] is None
    meta["means2d"].retain_grad()
    colors.sum().backward()
    assert meta["means2d"].grad.shape == (2, 50, 2)
    assert not hasattr(meta["means2d"], "absgrad")  # only set when asked for


def test_nothing_to_draw():
    scene = make_scene(20, 16, 12)
    scene["opacities"] = torch.full((20,), 0.5 * ALPHA_MIN, dtype=F64)  # can never reach 1/255
    colors, alphas, _ = rasterization(**scene, backgrounds=torch.ones(1, 3, dtype=F64))
    assert (alphas == 0).all() and (colors == 1).all()

    empty = torch.zeros(1, 0, dtype=F64)
    out, alpha = rasterize_to_pixels_sparse(
        empty.reshape(1, 0, 2),
        empty.reshape(1, 0, 3),
        empty.reshape(1, 0, 3),
        empty,
        empty,
        torch.zeros(1, 0, dtype=torch.int32),
        5,
        4,
    )
    assert out.shape == (1, 4, 5, 3) and (alpha == 0).all()

    # Opacity just above 1/255 and the mean 0.04 px off a pixel centre: that pixel is enumerated
    # (sigma = 8e-4 is inside the lenient bound) but its alpha = 0.9997/255 fails the exact test.
    args = (
        torch.tensor([[[2.54, 1.5]]], dtype=F64),
        torch.tensor([[[1.0, 0.0, 1.0]]], dtype=F64),
        torch.ones(1, 1, 3, dtype=F64),
        torch.tensor([[1.0005 * ALPHA_MIN]], dtype=F64),
        torch.ones(1, 1, dtype=F64),
        torch.tensor([[3]], dtype=torch.int32),
        5,
        4,
    )
    out, alpha = rasterize_to_pixels_sparse(*args)
    dense_out, dense_alpha = rasterize_to_pixels_dense(*args)
    assert (out == 0).all() and (alpha == 0).all()
    assert (dense_out == 0).all() and (dense_alpha == 0).all()
