"""Scene exposure (naka_gs_plugin.enhance.exposure) and its use by the Enhancer."""

import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.enhance.exposure import (
    KNEE,
    MAX_GAIN,
    METERED_TARGET,
    MIDDLE_GREY,
    MIN_GAMMA,
    _linear,
    apply_curve,
    apply_gain,
    apply_gamma,
    lift,
    lift_gain,
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


@pytest.mark.parametrize("metering, target", [("luminance", METERED_TARGET), ("mean", MIDDLE_GREY)])
def test_gain_lifts_a_dark_scene_to_the_target_keeping_black_and_linear_ratios(metering, target):
    views = _views(0.15)
    views[0][0, 0] = 0.0
    gain = lift_gain(views, target, metering)
    lifted = apply_gain(views, gain)
    assert 1.0 < gain < MAX_GAIN
    assert metered_level(lifted, metering) == pytest.approx(target, abs=0.01)
    assert lifted[0][0, 0].abs().max() < 1e-6  # black stays black
    for before, after in zip(views, lifted):
        order = before.flatten().argsort()
        assert (after.flatten()[order].diff() >= -1e-6).all()
        # Below the shoulder a longer exposure: every linear value times the same factor.
        lin_before, lin_after = _linear(before), _linear(after)
        below = (lin_before * gain < KNEE) & (lin_before > 0.01)
        assert_close(lin_after[below], lin_before[below] * gain, atol=1e-5, rtol=1e-4)


def test_gain_rolls_highlights_off_instead_of_clipping():
    ramp = torch.linspace(0.0, 1.0, 101)[:, None, None].expand(101, 1, 3).contiguous()
    out = apply_gain([ramp], 4.0)[0][:, 0, 0]
    assert (out.diff() >= 0).all()
    assert out.max() <= 1.0
    # The shoulder keeps highlights apart that a plain gain would clip to one white.
    clipped = _linear(ramp[:, 0])[:, 0] * 4.0 >= 1.0
    assert clipped.sum() > 10 and out[clipped].unique().numel() > 5


def test_power_flattens_where_gain_keeps_contrast():
    views = _views(0.12)
    power, gain = (apply_curve(views, c, lift(views, c)) for c in ("power", "gain"))
    assert metered_level(power) == pytest.approx(metered_level(gain), abs=0.01)
    assert sum(float(v.std()) for v in gain) > sum(float(v.std()) for v in power)


def test_scene_at_or_above_the_target_is_left_alone():
    views = _views(0.3) + [torch.full((8, 8, 3), 0.9)]
    views = [v.clamp(min=0.5) for v in views]
    assert lift_gamma(views) == 1.0 and lift_gain(views) == 1.0
    assert apply_gamma(views, 1.0)[0] is views[0] and apply_gain(views, 1.0)[0] is views[0]


def test_black_scene_gets_the_strongest_lift_and_stays_finite():
    views = [torch.zeros(8, 8, 3), torch.full((8, 8, 3), 1e-4)]
    gamma = lift_gamma(views)
    assert gamma == MIN_GAMMA
    out = apply_gamma(views, gamma)
    assert all(torch.isfinite(o).all() for o in out)
    assert out[0].max() == 0.0
    assert lift_gain(views) == MAX_GAIN
    assert apply_gain(views, MAX_GAIN)[0].max() == 0.0


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
    with pytest.raises(ValueError, match="gain or power"):
        lift(_views(0.1), "log")
    with pytest.raises(ValueError, match="enhance.exposure-curve"):
        Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure_curve="log"))
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


def test_configs_saved_before_the_curve_option_keep_the_power_curve():
    import yaml

    old = EnhanceConfig()
    del old.__dict__["exposure_curve"]
    assert yaml.load(yaml.dump(old), Loader=yaml.Loader).exposure_curve == "power"


@pytest.mark.parametrize("curve", ["gain", "power"])
def test_enhancer_lifts_a_dark_scene_and_none_keeps_the_network_exposure(curve):
    g = torch.Generator().manual_seed(1)
    # Dark views with one saturated lamp each: the min-max stretch keeps the rest dark.
    low = [(torch.rand(40, 48, 3, generator=g) * 0.03) for _ in range(3)]
    for im in low:
        im[:2, :2] = 1.0
    plain = Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure="none")).enhance_images(low)
    lifter = Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure_curve=curve))
    lifted = lifter.enhance_images(low)
    assert metered_level(plain) < 0.4
    assert metered_level(lifted) == pytest.approx(METERED_TARGET, abs=0.01)
    assert lifter.last_run["exposure_curve"] == curve
    expected = apply_curve(plain, curve, lifter.last_run["exposure_value"])
    for p, q in zip(expected, lifted):
        assert_close(q, p, atol=2e-5, rtol=0)
