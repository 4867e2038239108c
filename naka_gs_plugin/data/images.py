"""Reading captured images at their full bit depth.

Dark captures live in the bottom few percent of the range: an 8-bit read of a 16-bit PNG/TIFF
(what PIL, hence nerfstudio's ``InputDataset``, does for 48-bit RGB) keeps only the top byte and
turns most of a dark image into a handful of levels. Here 8- and 16-bit files (and float TIFFs)
are read with OpenCV at full precision into float32 sRGB in [0, 1].

Every read is checked in full: OpenCV fills the missing part of a truncated JPEG with grey and
only prints a libjpeg warning, so JPEGs are also decoded by PIL with truncated images refused
(whatever ``PIL.ImageFile.LOAD_TRUNCATED_IMAGES`` says); PNG/TIFF decoders already fail on a cut file.
A file is read only when it is a regular file (:func:`~naka_gs_plugin.data.safe_io.read_regular`): a FIFO or a
device in a scene is one line, never a read that blocks or never ends.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from jaxtyping import Float
from PIL import Image, ImageFile

from naka_gs_plugin.data.safe_io import atomic_write, read_regular
from naka_gs_plugin.errors import UserError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
"""Image file endings the plugin reads (compare with ``Path.suffix.lower()``)."""


class ImageReadError(UserError, ValueError):
    """An image that cannot be used; the message names the file and the fix."""


_RESTORE = "restore the complete file (copy it again from the camera or backup) or remove it from the scene"
REPLACE_IMAGE = "replace it with the image file, or remove it from the scene"
"""The fix of an image path that is not a regular file (a FIFO, a device, a folder)."""


def _fix(path: Path, user: str = _RESTORE) -> str:
    """How to mend an unreadable ``path``: the user's file is mended as ``user`` says; a cache file of ours is
    deleted."""
    from naka_gs_plugin.data.cache import cache_root_of  # here: the reader imports without nerfstudio (GPU side)

    root = cache_root_of(path)
    if root is None:
        return user
    return (
        f"this is a naka-gs cache file, not your photo: delete it (or the cache folder {root}, which NAKA_GS_CACHE "
        "sets) and run again to rebuild it"
    )


def _check_jpeg_complete(path: Path, data: bytes) -> None:
    """Decode ``data`` with PIL, refusing truncation (OpenCV would silently pad it with grey)."""
    saved = ImageFile.LOAD_TRUNCATED_IMAGES
    ImageFile.LOAD_TRUNCATED_IMAGES = False
    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()
    except OSError as err:
        raise ImageReadError(f"{path}: truncated or corrupt JPEG ({err}) -- {_fix(path)}") from None
    finally:
        ImageFile.LOAD_TRUNCATED_IMAGES = saved


def read_raw(path: Path) -> np.ndarray:
    """An image file decoded as stored (OpenCV: BGR(A) or grey, uint8/uint16/float), checked complete."""
    try:
        data = read_regular(path, fix=_fix(Path(path), REPLACE_IMAGE))
    except OSError as err:
        raise ImageReadError(f"{path}: cannot be read ({err.strerror or err}) -- {_fix(path)}") from None
    if not data:
        raise ImageReadError(f"{path}: empty file (0 bytes) -- {_fix(path)}")
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if arr is None:
        raise ImageReadError(f"{path}: unreadable image (truncated, corrupt or not a PNG/JPEG/TIFF) -- {_fix(path)}")
    if data[:3] == b"\xff\xd8\xff":
        _check_jpeg_complete(path, data)
    if arr.size == 0:
        raise ImageReadError(f"{path}: image has no pixels -- {_fix(path)}")
    return arr


def write_image(path: Path, bgr: np.ndarray, params: Sequence[int] = ()) -> Path:
    """Write ``bgr`` (OpenCV channel order) to ``path`` with :func:`cv2.imwrite`, published by
    :func:`atomic_write` only once it reads back whole.

    On a full disk OpenCV may report success for a file cut short; reading it back is what catches that.
    Raises :class:`OSError` (``path`` untouched) when the file cannot be written complete.
    """

    def write(tmp: Path) -> bool:
        if not cv2.imwrite(str(tmp), bgr, list(params)):
            return False
        try:
            back = read_raw(tmp)
        except ImageReadError:
            return False
        lossy = tmp.suffix.lower() in (".jpg", ".jpeg")
        return back.shape == bgr.shape and back.dtype == bgr.dtype and (lossy or np.array_equal(back, bgr))

    return atomic_write(path, write)


def read_rgb(path: Path, dtype: type = np.float32) -> Float[np.ndarray, "H W 3"]:
    """An image file as sRGB in [0, 1] (``dtype``, default float32): 8-bit /255, 16-bit /65535, float as stored.

    Grey images are repeated to 3 channels, alpha is dropped. Truncated, empty and non-image
    files, and non-finite pixels (float files), raise :class:`ImageReadError` rather than
    reaching training.
    """
    return as_float(read_stored(path), dtype)


def read_stored(path: Path) -> np.ndarray:
    """An image file as RGB ``[H, W, 3]`` at its own depth: ``uint8``/``uint16`` as stored (a quarter or
    half of :func:`read_rgb`'s memory, for holding many images), float files as float32 in [0, 1]."""
    return np.ascontiguousarray(_rgb(read_raw(path), path))


def to_rgb01(arr: np.ndarray, path: Path) -> Float[np.ndarray, "H W 3"]:
    """A :func:`read_raw` array as float32 RGB in [0, 1] (see :func:`read_rgb`; ``path`` names errors)."""
    return as_float(_rgb(arr, path))


def as_float(rgb: np.ndarray, dtype: type = np.float32) -> Float[np.ndarray, "H W 3"]:
    """A :func:`read_stored` array in [0, 1] as ``dtype``: ``uint8`` /255, ``uint16`` /65535, float as is."""
    if rgb.dtype == np.uint8:
        return rgb.astype(dtype) / dtype(255.0)
    if rgb.dtype == np.uint16:
        return rgb.astype(dtype) / dtype(65535.0)
    return rgb.astype(dtype)


def _rgb(arr: np.ndarray, path: Path) -> np.ndarray:
    """OpenCV's grey/BGR(A) -> RGB at the stored depth; float data checked finite and clipped to [0, 1]."""
    if arr.ndim == 2:
        arr = arr[:, :, None].repeat(3, axis=2)
    arr = arr[..., :3][..., ::-1]  # OpenCV's BGR(A) -> RGB
    if arr.dtype in (np.uint8, np.uint16):
        return arr
    arr = arr.astype(np.float32)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ImageReadError(
            f"{path}: {int(bad.any(axis=-1).sum())} pixels are NaN/Inf -- fix or re-export the image (8/16-bit PNG)"
        )
    return np.clip(arr, 0.0, 1.0)
