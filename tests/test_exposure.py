"""Scene exposure (naka_gs_plugin.enhance.exposure) and its use by the Enhancer."""

import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.enhance.exposure import (
    METERED_TARGET,
    MIDDLE_GREY,
    MIN_GAMMA,
    apply_gamma,
    lift_gamma,
    metered_level,
    scene_mean,
)
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer


def _views(mean: float, seed: int = 0) -> list:
    g = torch.Generator().manual_seed(seed)
    return [(torch.rand(24 + 8 * i, 32, 3, generator=g) * 2 * mean).clamp(0, 1) for i in range(3)]


@pytest.mark.parametrize("metering, target", [("luminance", METERED_TARGET), ("mean", MIDDLE_GREY)])
def test_dark_scene_is_lifted_to_the_target_by_one_shared_curve(metering, target):
    views = _views(0.15)
    gamma = lift_gamma(views, target, metering)
    lifted = apply_gamma(views, gamma)
    assert MIN_GAMMA < gamma < 1.0
    assert metered_level(lifted, metering) == pytest.approx(target, abs=0.01)
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


def test_luminance_metering_reads_a_dark_toned_scene_under_a_bright_sky_as_exposed():
    # Dark leaves (sRGB 0.25) with a quarter of the view bright sky (0.95): the mean sRGB value is low, but
    # the sky carries most of the light, as in a correctly exposed photo of such a scene.
    view = torch.full((40, 40, 3), 0.25)
    view[:10] = 0.95
    assert scene_mean([view]) < MIDDLE_GREY < METERED_TARGET < metered_level([view])
    assert lift_gamma([view]) == 1.0
    assert lift_gamma([view], MIDDLE_GREY, "mean") < 0.9


def test_luminance_metering_weighs_green_over_blue():
    green, blue = torch.zeros(8, 8, 3), torch.zeros(8, 8, 3)
    green[..., 1], blue[..., 2] = 0.6, 0.6
    assert scene_mean([green]) == scene_mean([blue])
    assert metered_level([green]) > METERED_TARGET > metered_level([blue])


def test_target_or_metering_out_of_range_is_refused():
    with pytest.raises(ValueError, match="in \\(0, 1\\)"):
        lift_gamma(_views(0.1), target=1.5)
    with pytest.raises(ValueError, match="luminance or mean"):
        lift_gamma(_views(0.1), metering="spot")
    with pytest.raises(ValueError, match="enhance.exposure "):
        Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure=0.0))
    with pytest.raises(ValueError, match="enhance.exposure-metering"):
        Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure_metering="spot"))


def test_configs_saved_before_the_metering_option_keep_mean_metering():
    import yaml

    old = EnhanceConfig()
    del old.__dict__["exposure_metering"]
    assert yaml.load(yaml.dump(old), Loader=yaml.Loader).exposure_metering == "mean"
    assert yaml.load(yaml.dump(EnhanceConfig()), Loader=yaml.Loader).exposure_metering == "luminance"


def test_enhancer_lifts_a_dark_scene_and_none_keeps_the_network_exposure():
    g = torch.Generator().manual_seed(1)
    # Dark views with one saturated lamp each: the min-max stretch keeps the rest dark.
    low = [(torch.rand(40, 48, 3, generator=g) * 0.01) for _ in range(3)]
    for im in low:
        im[:2, :2] = 1.0
    plain = Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure="none")).enhance_images(low)
    lifter = Enhancer(EnhanceConfig(correction="none", use_cache=False))
    lifted = lifter.enhance_images(low)
    assert metered_level(plain) < 0.4
    assert metered_level(lifted) == pytest.approx(METERED_TARGET, abs=0.01)
    gamma = lifter.last_run["exposure_gamma"]
    for p, q in zip(plain, lifted):
        assert_close(q, p.pow(gamma), atol=2e-5, rtol=0)
