"""Capture chroma: the enhanced image's brightness with the colour the dark capture itself recorded.

A shorter exposure scales every channel of a pixel's linear RGB by the same factor, so the chromaticity
``rgb / mean(rgb)`` in linear light is the same in the dark capture and in a normal-light photo of the
same lighting. The Naka-Rushton response is applied per channel and is strongly concave, which pulls the
channels together (0.02 and 0.04 become 0.29 and 0.44: a 2:1 ratio becomes 1.5:1), and the correction
network restores only part of it (LOM chair: saturation 0.12 after it, 0.33 in the normal-light photo).
Here each pixel keeps the enhanced image's linear brightness (mean of the channels) and takes its
chromaticity from the capture, low-pass filtered first because a dark capture's colour is mostly noise
at the pixel scale (as JPEG keeps colour at half resolution, the eye reads colour at a coarse scale).

Images are sRGB-encoded in [0, 1], channel-last ``[H, W, 3]``; the transfer happens in linear RGB.
"""

from __future__ import annotations

from jaxtyping import Float
from torch import Tensor

DEFAULT_BLUR = 3.0
"""Standard deviation, in pixels, of the Gaussian low-pass on the capture before its chromaticity is taken."""

_EPS = 1e-4
"""Linear level (a third of an 8-bit code) added to every channel before the ratio: a black capture pixel
gets a neutral chromaticity instead of 0/0, and the enhanced brightness there is kept."""


def capture_chroma(
    enhanced: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"], blur: float = DEFAULT_BLUR
) -> Float[Tensor, "H W 3"]:
    """``enhanced``'s linear brightness per pixel with the chromaticity of ``low`` (the capture it was
    enhanced from, same size) after a Gaussian blur of ``blur`` pixels; sRGB in [0, 1] in and out."""
    # kornia is imported here, not at module level: every ns-* command imports the method config
    # (hence this module) at start-up and must stay light.
    import kornia

    if enhanced.shape != low.shape:
        raise ValueError(f"capture chroma needs images of one size, got {tuple(enhanced.shape)} and {tuple(low.shape)}")
    if not blur > 0:
        raise ValueError(f"capture chroma blur must be > 0 pixels, got {blur!r}")
    kernel = max(3, int(3 * blur) | 1)  # odd, about +-1.5 sigma: the window the LOM measurements used
    capture = kornia.filters.gaussian_blur2d(
        low.permute(2, 0, 1)[None], (kernel, kernel), (blur, blur), border_type="replicate"
    )
    capture = kornia.color.rgb_to_linear_rgb(capture.clamp(0.0, 1.0))
    chromaticity = (capture + _EPS) / (capture.mean(dim=1, keepdim=True) + _EPS)
    linear = kornia.color.rgb_to_linear_rgb(enhanced.permute(2, 0, 1)[None].clamp(0.0, 1.0))
    out = linear.mean(dim=1, keepdim=True) * chromaticity
    return kornia.color.linear_rgb_to_rgb(out.clamp(0.0, 1.0))[0].permute(1, 2, 0)
