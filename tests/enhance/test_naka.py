"""Naka-Rushton enhancement: closed form, monotonicity, finiteness, per-scene statistics."""

import pytest
import torch

from naka_gs_plugin.enhance.naka import RANGE_EPS, linear_stretch, naka_enhance, naka_rushton, stretch_stats


def test_matches_closed_form():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(2, 5, 7, 3, generator=g, dtype=torch.float64) * 0.1
    for sigma, n in [(0.05, 1.0), (0.1, 0.7), (0.02, 2.0)]:
        r = img**n / (img**n + sigma**n)
        assert torch.allclose(naka_rushton(img, sigma, n), r, atol=1e-9)
        lo = r.flatten(1).min(1).values[:, None, None, None]
        hi = r.flatten(1).max(1).values[:, None, None, None]
        assert torch.allclose(naka_enhance(img, sigma, n), (r - lo) / (hi - lo), atol=1e-9)


def test_reference_values_at_default_sigma():
    x = torch.tensor([0.0, 0.05, 0.15, 1.0], dtype=torch.float64)
    assert torch.allclose(naka_rushton(x), torch.tensor([0.0, 0.5, 0.75, 1 / 1.05], dtype=torch.float64))


def test_monotone_in_input():
    x = torch.linspace(0, 1, 1001, dtype=torch.float64)
    for n in (0.5, 1.0, 2.0):
        assert (naka_rushton(x, 0.05, n).diff() > 0).all()
    img = x.reshape(1, 1001, 1).expand(1, 1001, 3)
    assert (naka_enhance(img)[0, :, 0].diff() >= 0).all()


@pytest.mark.parametrize("name,value", [("black", 0.0), ("constant", 0.3), ("saturated", 1.0)])
@pytest.mark.parametrize("n", [1.0, 0.5])
def test_degenerate_frames_finite_values_and_gradients(name, value, n):
    img = torch.full((1, 6, 5, 3), value, dtype=torch.float32, requires_grad=True)
    out = naka_enhance(img, 0.05, n)
    assert torch.isfinite(out).all()
    assert (out == 0).all(), f"{name}: zero stretch range must give all zeros, as the reference"
    out.sum().backward()
    assert torch.isfinite(img.grad).all()


def test_stretch_boundary_uses_range_eps():
    r = torch.zeros(1, 2, 2, 3)
    r[0, 0, 0, 0] = RANGE_EPS * 2
    lo, hi = stretch_stats(r)
    assert linear_stretch(r, lo, hi).max() == 1.0


def test_rejects_bad_parameters():
    with pytest.raises(ValueError):
        naka_rushton(torch.zeros(1, 1, 3), sigma=0.0)
