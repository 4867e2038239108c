"""Contact sheets: rows of images tiled into one picture (CLIs, the demo and the benches)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from jaxtyping import Shaped
from PIL import Image


def contact_sheet(rows: Sequence[Sequence[Shaped[np.ndarray, "H W 3"]]], max_width: int = 384) -> np.ndarray:
    """Tile images (float [0,1] or uint8, ``[H, W, 3]``) into a uint8 grid, each resized to the first's
    size scaled to at most ``max_width`` pixels wide."""
    first = rows[0][0]
    scale = min(1.0, max_width / first.shape[1])
    size = (max(1, int(first.shape[1] * scale)), max(1, int(first.shape[0] * scale)))

    def tile(img: np.ndarray) -> np.ndarray:
        arr = img if img.dtype == np.uint8 else (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        return np.asarray(Image.fromarray(arr).resize(size, Image.Resampling.BILINEAR))

    return np.concatenate([np.concatenate([tile(im) for im in row], axis=1) for row in rows], axis=0)
