"""Capture tone: no pixel of the enhanced view brighter, against its capture, than the view's typical gain.

A longer exposure scales the scene's linear light by one factor, so a normal-light photo's linear brightness
is the dark capture's times one gain wherever the capture recorded the scene: above the noise floor, below the
tone curve's shoulder. The enhancement does not keep that ratio: the Naka-Rushton response is concave and the
correction network, trained on LOL and LOM targets, lifts black, so the capture's shadows get a larger gain
than its mid-tones: lifted, grey-green shadows and flat contrast, worst on captures far darker than the
network's training pairs (RealX3D), where most of the view is shadow
(records/2026-11-28-bluehawaii-colour-diagnostics.md).

Here both brightnesses (the mean of the channels in linear light) are low-pass filtered, as a dark capture's
brightness is noise at the pixel scale, and the view's gain is the median of their ratio over the pixels the
capture records reliably (:data:`RELIABLE_CODES`). Wherever the enhanced view's local brightness exceeds that
gain times the capture's, its linear RGB is scaled down by the ratio (colour kept); nothing is scaled up:
highlights the Naka response compresses, or a capture too dark to meter, stay as they are. The scale is a ratio
of local means, so it is smooth: the tone follows the capture, the detail stays the enhancement's (scaling each
pixel to the filtered capture instead would replace the enhanced detail by the capture's blur).

The ceiling holds only below the capture's floor (:data:`FLOOR_CODES`), where the capture recorded no signal and
every lift is the enhancement's invention; where the capture measured the scene, the enhancement's tone is a
tone curve like a normal photo's (LOM's photos are not one gain over their captures), and a ceiling there costs
bright scenes their mid-tones (records/2026-11-28-bluehawaii-colour-diagnostics.md).

Images are sRGB-encoded in [0, 1], channel-last ``[H, W, 3]``; the ratio and the scaling are in linear RGB.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

DEFAULT_BLUR = 1.5
"""Standard deviation, in pixels, of the Gaussian low-pass on both brightnesses before their ratio is taken."""
RELIABLE_CODES = (2.0, 16.0)
"""8-bit sRGB code range of the filtered capture's brightness over which the view's gain is metered: above a
dark JPEG's floor (where noise is clipped at code 0, which lifts the mean), below its tone curve's shoulder."""
FLOOR_CODES = (2.0, 4.0)
"""8-bit code range of the filtered capture's brightness over which the ceiling fades: whole below the first (the
floor of :data:`RELIABLE_CODES`), none above the second."""
MIN_RELIABLE = 256
"""Fewer reliable pixels than this (a capture all black or all bright): the view is left as it is."""


def capture_tone(
    enhanced: Float[Tensor, "H W 3"],
    low: Float[Tensor, "H W 3"],
    blur: float = DEFAULT_BLUR,
    floor: Optional[Tuple[float, float]] = FLOOR_CODES,
) -> Float[Tensor, "H W 3"]:
    """``enhanced`` scaled down in linear light wherever its local brightness (a Gaussian of ``blur`` pixels) exceeds
    the view's median gain over that of ``low`` (the capture it came from, same size); sRGB in [0, 1] in and out.
    ``floor`` (8-bit codes ``(whole, none)``, ``whole < none``): the ceiling only where the filtered capture is under
    ``whole`` codes, fading out by ``none``; ``None``: everywhere."""
    import kornia  # not at module level: every ns-* command imports the method config at start-up

    if enhanced.shape != low.shape:
        raise ValueError(f"capture tone needs images of one size, got {tuple(enhanced.shape)} and {tuple(low.shape)}")
    if not blur > 0:
        raise ValueError(f"capture tone blur must be > 0 pixels, got {blur!r}")
    if floor is not None and not 0 <= floor[0] < floor[1]:
        raise ValueError(f"capture tone floor must be two codes 0 <= whole < none, got {floor!r}")
    kernel = max(3, int(3 * blur) | 1)

    def decode(codes: Tuple[float, float]) -> Tuple[float, float]:
        """Two 8-bit sRGB codes as linear light."""
        srgb = torch.tensor(codes).div(255.0).view(1, 2, 1).expand(3, 2, 1)
        return tuple(kornia.color.rgb_to_linear_rgb(srgb)[0, :, 0].tolist())

    def local_brightness(linear_rgb: Float[Tensor, "3 H W"]) -> Float[Tensor, "H W"]:
        mean = linear_rgb.mean(dim=0)[None, None]
        return kornia.filters.gaussian_blur2d(mean, (kernel, kernel), (blur, blur), border_type="replicate")[0, 0]

    capture = local_brightness(kornia.color.rgb_to_linear_rgb(low.permute(2, 0, 1).clamp(0.0, 1.0)))
    linear = kornia.color.rgb_to_linear_rgb(enhanced.permute(2, 0, 1).clamp(0.0, 1.0))
    brightness = local_brightness(linear)
    lo, hi = decode(RELIABLE_CODES)
    reliable = (capture >= lo) & (capture <= hi) & (brightness > 0)
    if int(reliable.sum()) < MIN_RELIABLE:
        return enhanced
    gain = (brightness[reliable] / capture[reliable]).median()
    scale = (gain * capture / brightness.clamp(min=1e-12)).clamp(max=1.0)
    if floor is not None:
        whole, none = decode(floor)
        weight = ((none - capture) / (none - whole)).clamp(0.0, 1.0)
        scale = 1.0 - weight * (1.0 - scale)
    return kornia.color.linear_rgb_to_rgb(linear * scale).permute(1, 2, 0)
