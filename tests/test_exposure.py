"""Scene exposure (naka_gs_plugin.enhance.exposure) and its use by the Enhancer."""

import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.enhance.exposure import MIDDLE_GREY, MIN_GAMMA, apply_gamma, lift_gamma, scene_mean
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer


def _views(mean: float, seed: int = 0) -> list:
    g = torch.Generator().manual_seed(seed)
    return [(torch.rand(24 + 8 * i, 32, 3, generator=g) * 2 * mean).clamp(0, 1) for i in range(3)]


def test_dark_scene_is_lifted_to_the_target_by_one_shared_curve():
    views = _views(0.15)
    gamma = lift_gamma(views)
    lifted = apply_gamma(views, gamma)
    assert MIN_GAMMA < gamma < 1.0
    assert scene_mean(lifted) == pytest.approx(MIDDLE_GREY, abs=0.01)
    for before, after in zip(views, lifted):  # one monotone curve: the order of values is kept
        assert_close(after, before.pow(gamma))
        order = before.flatten().argsort()
        assert (after.flatten()[order].diff() >= 0).all()


def test_scene_at_or_above_the_target_is_left_alone():
    views = _views(0.3) + [torch.full((8, 8, 3), 0.9)]
    views = [v.clamp(min=0.5) for v in views]
    assert lift_gamma(views) == 1.0
    assert apply_gamma(views, 1.0)[0] is views[0]


def test_black_scene_gets_the_strongest_lift_and_stays_finite():
    views = [torch.zeros(8, 8, 3), torch.full((8, 8, 3), 1e-4)]
    gamma = lift_gamma(views)
    assert gamma == MIN_GAMMA
    out = apply_gamma(views, gamma)
    assert all(torch.isfinite(o).all() for o in out)
    assert out[0].max() == 0.0


def test_target_out_of_range_is_refused():
    with pytest.raises(ValueError, match="in \\(0, 1\\)"):
        lift_gamma(_views(0.1), target=1.5)
    with pytest.raises(ValueError, match="enhance.exposure"):
        Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure=0.0))


def test_enhancer_lifts_a_dark_scene_and_none_keeps_the_network_exposure():
    g = torch.Generator().manual_seed(1)
    # Dark views with one saturated lamp each: the min-max stretch keeps the rest dark.
    low = [(torch.rand(40, 48, 3, generator=g) * 0.01) for _ in range(3)]
    for im in low:
        im[:2, :2] = 1.0
    plain = Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure="none")).enhance_images(low)
    lifter = Enhancer(EnhanceConfig(correction="none", use_cache=False))
    lifted = lifter.enhance_images(low)
    assert scene_mean(plain) < 0.3
    assert scene_mean(lifted) == pytest.approx(MIDDLE_GREY, abs=0.01)
    gamma = lifter.last_run["exposure_gamma"]
    for p, q in zip(plain, lifted):
        assert_close(q, p.pow(gamma), atol=2e-5, rtol=0)
