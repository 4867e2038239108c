"""Scene exposure (naka_gs_plugin.enhance.exposure) and its use by the Enhancer."""

import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.enhance.exposure import (
    KNEE,
    MAX_GAIN,
    METERED_TARGET,
    _gain,
    _luminance,
    _sample,
    apply_gain,
    lift_gain,
    metered_level,
)
from naka_gs_plugin.enhance.exposure import (
    srgb_to_linear as _linear,
)
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer


def _views(mean: float, seed: int = 0) -> list:
    g = torch.Generator().manual_seed(seed)
    return [(torch.rand(24 + 8 * i, 32, 3, generator=g) * 2 * mean).clamp(0, 1) for i in range(3)]


def test_gain_lifts_a_dark_scene_to_the_target_keeping_black_and_linear_ratios():
    views = _views(0.15)
    views[0][0, 0] = 0.0
    gain = lift_gain(views)
    lifted = apply_gain(views, gain)
    assert 1.0 < gain < MAX_GAIN
    assert metered_level(lifted) == pytest.approx(METERED_TARGET, abs=0.01)
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


def test_scene_at_or_above_the_target_is_left_alone():
    views = _views(0.3) + [torch.full((8, 8, 3), 0.9)]
    views = [v.clamp(min=0.5) for v in views]
    assert lift_gain(views) == 1.0
    assert apply_gain(views, 1.0)[0] is views[0]


def test_black_scene_gets_the_strongest_lift_and_stays_finite():
    views = [torch.zeros(8, 8, 3), torch.full((8, 8, 3), 1e-4)]
    assert lift_gain(views) == MAX_GAIN
    assert all(torch.isfinite(o).all() for o in apply_gain(views, MAX_GAIN))
    assert apply_gain(views, MAX_GAIN)[0].max() == 0.0


def test_luminance_metering_reads_a_dark_toned_scene_under_a_bright_sky_as_exposed():
    # Dark leaves (sRGB 0.25) with a quarter of the view bright sky (0.95): the mean sRGB value is low, but
    # the sky carries most of the light, as in a correctly exposed photo of such a scene.
    view = torch.full((40, 40, 3), 0.25)
    view[:10] = 0.95
    assert float(view.mean()) < 0.4613 < METERED_TARGET < metered_level([view])  # below middle grey in sRGB
    assert lift_gain([view]) == 1.0


def test_luminance_metering_weighs_green_over_blue():
    green, blue = torch.zeros(8, 8, 3), torch.zeros(8, 8, 3)
    green[..., 1], blue[..., 2] = 0.6, 0.6
    assert float(green.mean()) == float(blue.mean())
    assert metered_level([green]) > METERED_TARGET > metered_level([blue])


def test_target_out_of_range_is_refused():
    with pytest.raises(ValueError, match="in \\(0, 1\\)"):
        lift_gain(_views(0.1), target=1.5)
    with pytest.raises(ValueError, match="enhance.exposure "):
        Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure=0.0))


@pytest.mark.parametrize(
    "saved, warned",
    [
        ({"exposure_curve": "power"}, "exposure_curve 'power', retired"),
        ({"exposure_metering": "mean"}, "exposure_metering 'mean', retired"),
        ({"stats": "scene"}, "stats 'scene', retired"),
        ({"chroma": "network"}, "chroma 'network', retired"),
        ({"cache_dir": "/somewhere"}, "cache_dir '/somewhere', retired"),
    ],
)
def test_a_saved_config_naming_a_retired_option_loads_with_one_warning(saved, warned, capsys):
    """Runs saved before an option was retired load: the option is dropped, and one line says what runs now."""
    import yaml

    old = EnhanceConfig()
    old.__dict__.update({"stats": "image", "chroma": "capture", "exposure_curve": "gain"}, **saved)
    old.__dict__.setdefault("exposure_metering", "luminance")
    loaded = yaml.load(yaml.dump(old), Loader=yaml.Loader)
    assert loaded == EnhanceConfig() and not set(loaded.__dict__) - set(EnhanceConfig().__dict__)
    lines = [line for line in capsys.readouterr().out.splitlines() if "retired" in line]
    assert len(lines) == 1 and warned in lines[0], lines


def test_a_config_saved_now_or_with_the_retired_defaults_loads_silently(capsys):
    import yaml

    old = EnhanceConfig()
    old.__dict__.update(stats="image", chroma="capture", exposure_curve="gain", exposure_metering="luminance")
    for config in (EnhanceConfig(), old):
        assert yaml.load(yaml.dump(config), Loader=yaml.Loader) == EnhanceConfig()
    assert "retired" not in capsys.readouterr().out


def test_enhancer_lifts_a_dark_scene_and_none_keeps_the_network_exposure():
    g = torch.Generator().manual_seed(1)
    # Dark views with one saturated lamp each: the min-max stretch keeps the rest dark.
    low = [(torch.rand(40, 48, 3, generator=g) * 0.03) for _ in range(3)]
    for im in low:
        im[:2, :2] = 1.0
    plain = Enhancer(EnhanceConfig(correction="none", use_cache=False, exposure="none")).enhance_images(low)
    lifter = Enhancer(EnhanceConfig(correction="none", use_cache=False))
    lifted = lifter.enhance_images(low)
    assert metered_level(plain) < 0.4
    assert metered_level(lifted) == pytest.approx(METERED_TARGET, abs=0.01)
    expected = apply_gain(plain, lifter.last_run["exposure_gain"])
    for p, q in zip(expected, lifted):
        assert_close(q, p, atol=2e-5, rtol=0)


def test_lift_gain_is_the_bisection_of_the_metered_level_of_apply_gain():
    # The readable definition: bisect the gain on the metering of `_gain`'s sRGB output of the sampled pixels.
    # The fast path meters sorted linear values (the part below the knee as one sum); scenes with bright
    # highlights put many pixels through the shoulder at the gains the bisection tries.
    g = torch.Generator().manual_seed(3)
    for mean, highlights in ((0.15, 0.0), (0.2, 0.1), (0.25, 0.2)):
        views = _views(mean, seed=int(100 * mean))
        for view in views:  # sRGB 0.75: linear 0.52, past the knee at gains above 1.5
            view[torch.rand(view.shape[:2], generator=g) < highlights] = 0.75
        sample = _sample(views, 7)  # lift_gain's default stride
        goal = float(_linear(torch.full((1, 3), METERED_TARGET))[0, 0])
        lo, hi = 1.0, MAX_GAIN
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _luminance(_gain(sample, mid)) < goal else (lo, mid)
        expected = 0.5 * (lo + hi)
        assert 1.0 < expected < MAX_GAIN
        assert lift_gain(views) == pytest.approx(expected, rel=1e-9)
