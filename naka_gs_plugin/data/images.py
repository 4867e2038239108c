"""Reading captured images at their full bit depth.

Dark captures live in the bottom few percent of the range: an 8-bit read of a 16-bit PNG/TIFF
(what PIL, hence nerfstudio's ``InputDataset``, does for 48-bit RGB) keeps only the top byte and
turns most of a dark image into a handful of levels. Here 8- and 16-bit files (and float TIFFs)
are read with OpenCV at full precision into float32 sRGB in [0, 1].
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from jaxtyping import Float


class ImageReadError(ValueError):
    """An image that cannot be used; the message names the file and the fix."""


def read_rgb(path: Path) -> Float[np.ndarray, "H W 3"]:
    """An image file as float32 sRGB in [0, 1]: 8-bit /255, 16-bit /65535, float as stored.

    Grey images are repeated to 3 channels, alpha is dropped. Non-finite pixels (float files)
    are rejected rather than propagated into training.
    """
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if arr is None:
        raise ImageReadError(f"{path}: unreadable image -- replace it with a valid PNG/JPEG/TIFF")
    if arr.ndim == 2:
        arr = arr[:, :, None].repeat(3, axis=2)
    arr = arr[..., :3][..., ::-1]  # OpenCV's BGR(A) -> RGB
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    if arr.dtype == np.uint16:
        return arr.astype(np.float32) / 65535.0
    arr = arr.astype(np.float32)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ImageReadError(
            f"{path}: {int(bad.any(axis=-1).sum())} pixels are NaN/Inf -- fix or re-export the image (8/16-bit PNG)"
        )
    return np.clip(arr, 0.0, 1.0)

