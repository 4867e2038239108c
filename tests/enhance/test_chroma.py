"""Capture chroma (naka_gs_plugin.enhance.chroma) and its use by the Enhancer."""

import kornia
import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer


def _patches(seed: int = 0) -> torch.Tensor:
    """A 48x64 sRGB image of four flat, saturated colour patches (linear RGB in [0.05, 0.6])."""
    g = torch.Generator().manual_seed(seed)
    colours = torch.rand(4, 3, generator=g) * 0.55 + 0.05
    linear = colours.view(2, 2, 1, 1, 3).expand(2, 2, 24, 32, 3).permute(0, 2, 1, 3, 4).reshape(48, 64, 3)
    return kornia.color.linear_rgb_to_rgb(linear.permute(2, 0, 1)).permute(1, 2, 0)


INNER = torch.zeros(48, 64, dtype=torch.bool)
"""The four patches of :func:`_patches` away from the borders the blur mixes."""
for _rows in (slice(6, 18), slice(30, 42)):
    for _cols in (slice(8, 24), slice(40, 56)):
        INNER[_rows, _cols] = True


def _linear(image: torch.Tensor) -> torch.Tensor:
    return kornia.color.rgb_to_linear_rgb(image.permute(2, 0, 1)).permute(1, 2, 0)


def test_the_captures_colour_comes_back_at_the_enhanced_brightness():
    truth = _patches()
    # A dark capture of the same scene: every channel scaled by the same factor in linear light.
    low = kornia.color.linear_rgb_to_rgb((_linear(truth) * 0.1).permute(2, 0, 1)).permute(1, 2, 0)
    # An enhanced view with the right brightness but washed-out colour (half-way to grey).
    lin = _linear(truth)
    grey = lin.mean(-1, keepdim=True)
    washed = kornia.color.linear_rgb_to_rgb((grey + 0.5 * (lin - grey)).permute(2, 0, 1)).permute(1, 2, 0)
    out = capture_chroma(washed, low, blur=1.0)
    inner = (slice(4, 20), slice(4, 28))  # away from the patch borders the blur mixes
    assert_close(out[inner], truth[inner], atol=2e-3, rtol=0)
    assert_close(_linear(out).mean(-1)[inner], grey[..., 0][inner], atol=1e-3, rtol=0)
    assert (out - washed).abs()[inner].max() > 0.05  # it did change the colour


def test_a_black_capture_keeps_the_enhanced_brightness_in_neutral_grey():
    enhanced = _patches(1)
    out = capture_chroma(enhanced, torch.zeros_like(enhanced))
    assert torch.isfinite(out).all()
    assert_close(out[..., 0], out[..., 1])
    assert_close(out[..., 1], out[..., 2])
    assert_close(_linear(out).mean(-1), _linear(enhanced).mean(-1), atol=1e-3, rtol=0)


def test_sizes_and_blur_are_checked():
    image = _patches()
    with pytest.raises(ValueError, match="one size"):
        capture_chroma(image, image[:10])
    with pytest.raises(ValueError, match="blur"):
        capture_chroma(image, image, blur=0.0)
    with pytest.raises(ValueError, match="enhance.chroma-blur"):
        Enhancer(EnhanceConfig(correction="none", use_cache=False, chroma_blur=-1.0))


def test_enhancer_takes_colour_from_the_capture_where_naka_alone_changes_it():
    truth = _patches(2)
    low = [kornia.color.linear_rgb_to_rgb((_linear(truth) * f).permute(2, 0, 1)).permute(1, 2, 0) for f in (0.02, 0.03)]
    enhancer = Enhancer(EnhanceConfig(correction="none", exposure="none", tone="network", use_cache=False))
    capture = enhancer.enhance_images(low)
    assert [stage.name for stage in enhancer.view_stages] == ["naka", "chroma"]
    plain = [naka_enhance(im) for im in low]

    def chromaticity(im: torch.Tensor) -> torch.Tensor:
        return _linear(im)[INNER] / _linear(im)[INNER].mean(-1, keepdim=True)

    # Naka's per-channel response and stretch change the channel ratios; the capture keeps the truth's.
    assert (chromaticity(plain[0]) - chromaticity(truth)).abs().max() > 0.3
    unclipped = _linear(capture[0])[INNER].amax(-1) < 0.99  # bright colours clip
    assert unclipped.float().mean() > 0.5
    assert_close(chromaticity(capture[0])[unclipped], chromaticity(truth)[unclipped], atol=0.02, rtol=0)


def test_images_smaller_than_the_blur_window_work():
    tiny = _patches()[:2, :3]
    out = capture_chroma(tiny, tiny * 0.1, blur=3.0)
    assert out.shape == (2, 3, 3) and torch.isfinite(out).all()
