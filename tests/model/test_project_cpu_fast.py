"""The compiled projection and SH colours of cpu-fast against the torch reference (projection.py):
values, radii and hand-written gradients vs torch autograd, on the hard cases."""

from __future__ import annotations

import pytest
import torch

from naka_gs_plugin.model import project_cpu_fast as fast
from naka_gs_plugin.model import projection as ref
from tests.helpers import make_scene

F32, F64 = torch.float32, torch.float64


def _close(a, b, rtol):
    """Per element within ``rtol``, with a floor of 1e-7 of the largest reference magnitude."""
    return torch.allclose(a, b, rtol=rtol, atol=1e-7 * float(b.abs().max().clamp(min=1e-30)))


def _project(fn, scene, calc_comp, weights):
    inputs = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales")}
    proj = fn(
        inputs["means"],
        inputs["quats"],
        inputs["scales"],
        scene["viewmats"],
        scene["Ks"],
        scene["width"],
        scene["height"],
        eps2d=0.3,
        calc_compensations=calc_comp,
    )
    outs = [proj.means2d, proj.depths[..., None], proj.conics] + ([proj.compensations[..., None]] if calc_comp else [])
    flat = torch.cat(outs, -1)
    (flat * weights[..., : flat.shape[-1]]).sum().backward()
    return proj, {k: v.grad for k, v in inputs.items()}


@pytest.mark.parametrize("calc_comp", [False, True], ids=["classic", "antialiased"])
def test_projection_matches_reference_float64(calc_comp):
    scene = make_scene(300, 50, 40, n_cams=3, dtype=F64, hard=True, seed=1)
    scene["scales"][12] = torch.tensor([40.0, 1e-9, 2.0], dtype=F64)  # flat and huge
    scene["means"][13] = torch.tensor([1.8, 0.0, 2.0], dtype=F64)  # outside, visible: the Jacobian clamp
    scene["means"][14] = torch.tensor([-0.3, 1.5, 2.0], dtype=F64)
    scene["scales"][13:15] = 0.5
    scene["quats"][15] = torch.tensor([1e-13, 0.0, 0.0, 0.0], dtype=F64)  # below F.normalize's eps
    weights = torch.randn(3, 300, 7, generator=torch.Generator().manual_seed(3), dtype=F64)
    weights[0, 40:60] = 0.0  # visible in camera 0 but no gradient from it (composited by no pixel)
    weights[:, 60:80] = 0.0  # from no camera
    p_fast, g_fast = _project(fast.project_gaussians, scene, calc_comp, weights)
    p_ref, g_ref = _project(ref.project_gaussians, scene, calc_comp, weights)
    assert torch.equal(p_fast.radii, p_ref.radii)
    assert (p_ref.radii[:, [9, 10]] == 0).all() and (p_ref.radii[0, [0, 1, 12, 13, 14]] > 0).all()
    assert (p_ref.radii == 0).any() and (p_ref.radii > 0).sum() > 600
    for name in ("means2d", "depths", "conics") + (("compensations",) if calc_comp else ()):
        assert _close(getattr(p_fast, name), getattr(p_ref, name), 1e-10), name
    assert (p_fast.compensations is None) == (not calc_comp)
    for name in ("means", "quats", "scales"):
        assert g_ref[name].abs().max() > 0, name
        assert _close(g_fast[name], g_ref[name], 1e-8), name
    culled = (p_ref.radii == 0).all(0)
    assert (g_fast["means"][culled] == 0).all() and (g_fast["quats"][culled] == 0).all()
    assert (p_ref.radii[0, 40:80] > 0).sum() > 20 and (g_ref["scales"][40:60] != 0).any()
    for name in ("means", "quats", "scales"):
        assert (g_fast[name][60:80] == 0).all(), name


def test_projection_float32_is_the_float64_reference_rounded():
    """float32 inputs are projected in float64: the float64 reference's results, rounded (the torch
    path's own float32 arithmetic loses ~1e-3 of the compensation to cancellation here)."""
    scene = make_scene(2000, 64, 48, n_cams=2, dtype=F32, hard=True, seed=4)
    scene64 = {k: v.double() if torch.is_tensor(v) else v for k, v in scene.items()}
    weights = torch.randn(2, 2000, 7, generator=torch.Generator().manual_seed(1))
    p_fast, g_fast = _project(fast.project_gaussians, scene, True, weights)
    p_ref, g_ref = _project(ref.project_gaussians, scene64, True, weights.double())
    assert p_fast.means2d.dtype == F32 and p_fast.radii.dtype == torch.int32
    assert torch.equal(p_fast.radii, p_ref.radii) and (p_ref.radii > 0).sum() > 3000
    for name in ("means2d", "conics", "compensations", "depths"):
        assert _close(getattr(p_fast, name), getattr(p_ref, name).float(), 1e-6), name
    for name in ("means", "quats", "scales"):
        assert (g_fast[name] - g_ref[name]).abs().max() <= 1e-6 * g_ref[name].abs().max(), name


@pytest.mark.parametrize("per_camera", [False, True], ids=["shared", "per-camera"])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colors_match_reference_float64(degree, per_camera):
    gen = torch.Generator().manual_seed(degree)
    n, n_cams = 200, 2
    scene = make_scene(n, 30, 20, n_cams=n_cams, sh_degree=3, dtype=F64, seed=degree)
    means = scene["means"]
    means[0] = -scene["viewmats"][0, :3, 3]  # at camera 0's centre: a zero direction
    shape = (n_cams, n, 16, 3) if per_camera else (n, 16, 3)
    coeffs = 2.0 * torch.randn(shape, generator=gen, dtype=F64)  # large enough for the clamp at 0
    weights = torch.randn(n_cams, n, 3, generator=gen, dtype=F64)
    weights[0, 5:40] = 0.0  # Gaussians camera 0 does not composite: no colour gradient from it
    weights[:, 40:60] = 0.0  # nor from any camera
    results = []
    for fn in (fast.sh_colors, ref.sh_colors):
        m, c = means.clone().requires_grad_(), coeffs.clone().requires_grad_()
        coeffs_in = c.expand(n_cams, *c.shape) if (fn is ref.sh_colors and not per_camera) else c
        out = fn(m, coeffs_in, scene["viewmats"], degree)
        (out * weights).sum().backward()
        results.append((out, m.grad, c.grad))
    (o_f, m_f, c_f), (o_r, m_r, c_r) = results
    assert (o_r == 0).any() and (o_r > 0).any()  # the clamp is exercised
    assert _close(o_f, o_r, 1e-12)
    assert _close(c_f, c_r, 1e-10)
    assert (c_f[..., (degree + 1) ** 2 :, :] == 0).all()
    assert (c_f[..., 40:60, :, :] == 0).all() and c_f[..., 5:40, :, :].abs().max() > 0
    if degree == 0:
        assert m_f is None and m_r is None  # degree 0 does not depend on the direction
    else:
        assert m_r.abs().max() > 0 and _close(m_f, m_r, 1e-8)
        assert (m_f[40:60] == 0).all()


@pytest.mark.parametrize("degree", [1, 3])
def test_sh_colors_from_splatfacto_s_two_parameters_are_the_concatenation_s_bits(degree):
    """``(features_dc, features_rest)`` as they are give the colours and gradients of their [N, K, 3]
    concatenation bit for bit (float32, as training), each gradient in its own parameter's layout."""
    gen = torch.Generator().manual_seed(degree)
    scene = make_scene(300, 30, 20, n_cams=1, sh_degree=3, seed=degree)
    dc, rest = torch.randn(300, 3, generator=gen), torch.randn(300, 15, 3, generator=gen)
    weights = torch.randn(1, 300, 3, generator=gen)
    results = []
    for pair in (False, True):
        m, d, r = (x.clone().requires_grad_() for x in (scene["means"], dc, rest))
        coeffs = (d, r) if pair else torch.cat((d[:, None, :], r), dim=1)
        out = fast.sh_colors(m, coeffs, scene["viewmats"], degree)
        (out * weights).sum().backward()
        results.append((out, m.grad, d.grad, r.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b)
    assert results[1][3].is_contiguous() and results[1][3][:, (degree + 1) ** 2 - 1 :].count_nonzero() == 0


def test_camera_gradients_defer_to_the_reference():
    scene = make_scene(50, 30, 20, n_cams=1, dtype=F64, seed=2)
    viewmats = scene["viewmats"].clone().requires_grad_()
    proj = fast.project_gaussians(scene["means"], scene["quats"], scene["scales"], viewmats, scene["Ks"], 30, 20)
    colors = fast.sh_colors(scene["means"], scene["colors"], viewmats, 3)
    (proj.means2d.sum() + colors.sum()).backward()
    assert viewmats.grad is not None and viewmats.grad.abs().max() > 0


def test_bad_sh_degree_is_refused():
    means = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="needs 9 coefficients"):
        fast.sh_colors(means, torch.zeros(2, 4, 3), torch.eye(4)[None], 2)
    with pytest.raises(ValueError, match="0..3"):
        fast.sh_colors(means, torch.zeros(2, 25, 3), torch.eye(4)[None], 4)
