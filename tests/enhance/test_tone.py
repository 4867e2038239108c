"""Capture tone (naka_gs_plugin.enhance.tone) and its place in the enhancement chain."""

import kornia
import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.enhance.tone import capture_tone


def _srgb(linear: torch.Tensor) -> torch.Tensor:
    return kornia.color.linear_rgb_to_rgb(linear.permute(2, 0, 1)).permute(1, 2, 0)


def _linear(image: torch.Tensor) -> torch.Tensor:
    return kornia.color.rgb_to_linear_rgb(image.permute(2, 0, 1)).permute(1, 2, 0)


def _scene() -> torch.Tensor:
    """A 64x96 linear-light scene: a horizontal brightness ramp from deep shadow (0.004) to 0.5, warm-tinted."""
    ramp = torch.logspace(-2.4, -0.3, 96).expand(64, 96)
    return ramp[..., None] * torch.tensor([1.2, 1.0, 0.7])


def test_lifted_shadows_below_the_captures_floor_come_down_to_the_views_median_gain_with_their_colour():
    truth = _scene()
    low = _srgb(truth / 40)  # a dark capture: every channel scaled alike in linear light
    lifted = truth**0.6 * torch.tensor([1.2, 1.0, 0.7]) ** 0.4  # a concave tone: the shadows gain most
    enhanced = _srgb(lifted.clamp(0, 1))
    out = capture_tone(enhanced, low, blur=1.0)
    before, after = _linear(enhanced), _linear(out)
    capture = _linear(low).mean(-1)
    gain_in, gain_out = before.mean(-1) / capture, after.mean(-1) / capture
    inner = (slice(4, 60), slice(4, 92))  # away from the borders the blur mixes
    # the capture's reliable range (2-16 codes) holds the middle columns: their median gain is the ceiling
    codes = low.mean(-1) * 255
    ceiling = gain_in[(codes >= 2) & (codes <= 16)].median()
    assert (after <= before + 1e-4).all()  # never brighter
    floor, measured = codes[inner] < 1.8, codes[inner] > 4.3  # under the floor; above the fade (2-4 codes)
    lifted_above = measured & (gain_in[inner] > ceiling * 1.02)  # mid-tones the enhancement lifted, kept so
    assert floor.float().mean() > 0.1 and lifted_above.float().mean() > 0.02
    assert (gain_in[inner][floor] > ceiling * 1.05).all()
    assert_close(gain_out[inner][floor], torch.full_like(gain_out[inner][floor], float(ceiling)), rtol=0.03, atol=0)
    assert_close(after[inner][measured], before[inner][measured], atol=2e-5, rtol=0)
    chroma = after[inner] / after[inner].mean(-1, keepdim=True)
    assert_close(chroma, before[inner] / before[inner].mean(-1, keepdim=True), atol=2e-3, rtol=0)


def test_a_capture_above_its_floor_keeps_the_enhancements_tone_which_the_ceiling_everywhere_would_flatten():
    truth = _scene()
    low = _srgb(truth / 2)  # a bright capture (LOM-like): every pixel above 4 codes
    assert (low.mean(-1) * 255).min() > 4.3
    enhanced = _srgb((truth**0.6).clamp(0, 1))
    assert_close(capture_tone(enhanced, low), enhanced, atol=2e-5, rtol=0)
    assert (capture_tone(enhanced, low, floor=None) < enhanced - 0.015).any()


def test_a_capture_with_nothing_to_meter_leaves_the_view_alone():
    enhanced = _srgb(_scene())
    assert torch.equal(capture_tone(enhanced, torch.zeros_like(enhanced)), enhanced)  # all black
    assert torch.equal(capture_tone(enhanced, torch.full_like(enhanced, 0.8)), enhanced)  # all bright


def test_sizes_and_blur_are_checked():
    image = _srgb(_scene())
    with pytest.raises(ValueError, match="one size"):
        capture_tone(image, image[:10])
    with pytest.raises(ValueError, match="blur"):
        capture_tone(image, image, blur=0.0)
    with pytest.raises(ValueError, match="floor"):
        capture_tone(image, image, floor=(4.0, 2.0))


def test_capture_tone_is_the_default_stage_after_capture_chroma():
    default = Enhancer(EnhanceConfig(correction="none"))
    network = Enhancer(EnhanceConfig(correction="none", tone="network"))
    assert [s.name for s in default.view_stages] == ["naka", "chroma", "tone"]
    assert [s.name for s in network.view_stages] == ["naka", "chroma"]
    assert default.key() != network.key()


def test_runs_saved_before_capture_tone_load_with_the_networks_tone():
    state = dict(EnhanceConfig().__dict__)
    del state["tone"]
    config = EnhanceConfig.__new__(EnhanceConfig)
    config.__setstate__(state)
    assert config.tone == "network"


def test_the_scale_is_smooth_so_the_enhanced_detail_is_kept():
    truth = _scene()
    low = _srgb(truth / 40)
    checker = (torch.arange(64)[:, None] // 2 + torch.arange(96)[None] // 2) % 2
    lifted = truth**0.6 * (1 + 0.2 * checker[..., None])  # enhanced detail the capture does not carry
    enhanced = _srgb(lifted.clamp(0, 1))
    before, after = _linear(enhanced).mean(-1), _linear(capture_tone(enhanced, low, blur=1.5)).mean(-1)
    scale = (after / before)[4:60, 4:92]
    assert scale.min() < 0.8  # the shadows came down
    local = torch.nn.functional.avg_pool2d(scale[None, None], 4, stride=4)[0, 0]
    spread = (scale.unfold(0, 4, 4).unfold(1, 4, 4) - local[..., None, None]).abs().amax()
    assert spread < 0.05, f"the scale varies by {spread:.3f} within 4x4 blocks: it would flatten the 20 % texture"
