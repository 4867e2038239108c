"""``lowlight-data``: the scene layout shared by RealX3D and LOM (and written by our simulator).

::

    <scene>/transforms_train.json   frames -> low-light training images (e.g. train/0001.JPG, low/3.JPG)
    <scene>/transforms_val.json     optional; used for the ``val`` split when present
    <scene>/transforms_test.json    frames -> normal-light ground truth (images may be absent: RealX3D)

Each json holds intrinsics ``fl_x fl_y cx cy w h`` (pixels; per-frame keys override), optional
OpenCV distortion ``k1 k2 (k3 k4) p1 p2``, and per frame ``file_path`` (relative to the scene) and
``transform_matrix``: camera-to-world in the OpenGL convention (x right, y up, looking down -z), which
is nerfstudio's own, so no axis swap is needed.

Normalization: nerfstudio's ``auto_orient_and_center_poses`` plus auto-scale (largest camera
coordinate -> 1), computed **on the training poses only** and applied to every split, so all splits
and any external point cloud share one frame (``dataparser_transform`` [3, 4] and
``dataparser_scale``; :func:`to_normalized_frame` maps world points into it).

``downscale_factor`` writes downscaled copies to a writable cache (the scene may be read-only).
Eval frames whose images are all missing still load their poses; ``metadata["has_ground_truth"]``
is then ``False`` and the datamanager refuses metrics with a one-line message. An eval json whose images are dark
captures, not normal-light truth (``naka-gs-process-data`` writes such scenes), says so with the top-level key
``"eval_truth": "dark"`` (default ``"normal-light"``): ``metadata["eval_truth"]``, which the datamanager labels.

Every file read (the transforms jsons, every split's images) must be a regular file: a FIFO, a device
(``file_path: /dev/zero``) or a socket is refused in one line naming it before anything is opened
(:func:`~naka_gs_plugin.data.safe_io.regular_file`), and so is a path longer than the system allows.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Literal, Optional, Tuple, Type

import cv2
import numpy as np
import torch
from jaxtyping import Float
from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from torch import Tensor

from naka_gs_plugin.data.cache import default_cache_dir, read_sealed, seal
from naka_gs_plugin.data.images import (
    IMAGE_SUFFIXES,
    REPLACE_IMAGE,
    ImageReadError,
    read_raw,
    to_rgb01,
    write_image,
)
from naka_gs_plugin.data.safe_io import input_stat, open_regular, read_regular, regular_file, shown_path
from naka_gs_plugin.errors import UserError

MAX_AUTO_RESOLUTION = 1600
"""Auto downscale picks the smallest power of two bringing the longer side to at most this (as nerfstudio-data)."""

MAX_FOCAL_RATIO = 100.0
"""Largest focal length accepted, in image sizes (a 0.6 degree field of view): larger is a unit error."""
ROTATION_TOLERANCE = 1e-2
"""Largest ``|R^T R - I|`` entry accepted for a pose's rotation block (exports round to ~1e-7)."""
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
DISTORTION_SCALE_RANGE = (0.5, 2.0)
"""Accepted radial scale of the distortion at the image corner (distorted / undistorted radius).

Measured: LOM's calibrations give 1.005 or less, RealX3D has none (1.0); strong wide-angle lenses
in OpenCV's model (k1 ~ -0.3, k2 ~ 0.1) give ~0.7. Beyond this range the coefficients are a typo or
another model's (fisheye), and the undistorted image is meaningless."""
MAX_CAMERA_SPREAD = 100.0
"""Largest distance of a training camera from the cameras' median centre, in median distances.

Measured on the 12 real scenes in ../shared/data (LOM bike/chair/shrub/sofa, the 8 RealX3D scenes):
1.9 to 5.4 (LOM chair). A camera 100x out is a broken pose (wrong units, a tracking failure); it would
also shrink the normalized scene by that factor, since auto-scale fits the farthest camera into [-1, 1].
Two cameras are never refused: both are equally far from their centre."""
MIN_IMAGE_SIDE = 8
"""Smallest image side accepted, in pixels: training starts at 1/4 size (splatfacto's two downscales), and a view
needs 2 pixels a side there (a 1 px view breaks the loss's tensors)."""


class LowLightDataError(UserError, ValueError):
    """A scene file is malformed; the message names the file and the fix, on one line."""


@dataclass
class LowLightDataParserConfig(DataParserConfig):
    """Reads ``transforms_{train,val,test}.json`` scenes (RealX3D, LOM, naka-gs-sim)."""

    _target: Type = field(default_factory=lambda: LowLightDataParser)
    data: Path = Path("scene")
    """Scene folder holding transforms_train.json and transforms_test.json."""
    downscale_factor: Optional[int] = None
    """Integer image downscale; None picks the smallest power of 2 with the longer side <= 1600 px."""
    scale_factor: float = 1.0
    """Extra scale applied to the normalized poses."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """Orientation of the normalized frame (nerfstudio's auto_orient_and_center_poses)."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """Centring of the normalized frame."""
    auto_scale_poses: bool = True
    """Scale so that the largest absolute camera coordinate is 1 (splatfacto assumes a unit scene)."""

    def __setstate__(self, state: dict) -> None:
        """Runs saved while ``cache_dir`` was an option: every cache now lives in ``$NAKA_GS_CACHE``."""
        if state.pop("cache_dir", None) is not None:
            CONSOLE.log(
                "[naka-gs] warning: this run's config names a dataparser cache-dir, retired: every cache lives "
                "in $NAKA_GS_CACHE (default ~/.cache/naka-gs); set it to keep using that folder",
                markup=False,
            )
        self.__dict__.update(state)


def _fail(path: Path, problem: str, fix: str) -> LowLightDataError:
    return LowLightDataError(f"{path}: {problem} -- {fix}")


def load_transforms(path: Path) -> dict:
    """Read and validate a transforms json; raises :class:`LowLightDataError` naming the file (a FIFO or a device
    there: :class:`~naka_gs_plugin.data.safe_io.InputFileError`, before it is opened)."""
    fix = "replace it with the transforms json file"
    if not regular_file(path, fix=fix):
        raise _fail(
            path, "file not found", "every lowlight-data scene needs transforms_train.json and transforms_test.json"
        )
    try:
        # utf-8-sig: a byte-order mark (Windows editors) too
        meta = json.loads(read_regular(path, fix=fix).decode("utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise _fail(
            path, f"malformed json ({err})", "fix the json syntax (e.g. check with `python -m json.tool`)"
        ) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise _fail(path, "no 'frames' list", "the file must be an object with a 'frames' list")
    return meta


def _number(value: object, what: str, path: Path) -> float:
    """``value`` as a float; strings, booleans and nulls are refused (a json typo, not a number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(path, f"{what} is {value!r}, not a number", "write it as a json number")
    return float(value)


def _intrinsic(meta: dict, frame: dict, key: str, path: Path, where: str) -> float:
    value = frame.get(key, meta.get(key))
    if value is None and key in ("fl_x", "fl_y") and "camera_angle_x" in meta:
        w = _number(frame.get("w", meta.get("w", 0)), f"{where} 'w'", path)
        angle = _number(meta["camera_angle_x"], "'camera_angle_x'", path)
        if not 0.0 < angle < math.pi:
            raise _fail(path, f"'camera_angle_x' is {angle} rad", "give the horizontal field of view in (0, pi) rad")
        return 0.5 * w / math.tan(0.5 * angle)
    if value is None and key in ("cx", "cy"):
        size = frame.get("w" if key == "cx" else "h", meta.get("w" if key == "cx" else "h", 0))
        return 0.5 * _number(size, f"{where} '{'w' if key == 'cx' else 'h'}'", path)
    if value is None:
        raise _fail(path, f"missing intrinsic '{key}'", "give fl_x fl_y cx cy w h at the top level or per frame")
    return _number(value, f"{where} '{key}'", path)


def _check_intrinsics(intr: List[float], path: Path, where: str) -> None:
    """Finite, positive focal lengths and size, a focal length at most :data:`MAX_FOCAL_RATIO` image sizes."""
    fx, fy, cx, cy, w, h = intr
    if not all(math.isfinite(v) for v in intr):
        raise _fail(path, f"{where} intrinsics fl_x fl_y cx cy w h = {intr} are not all finite", "fix the camera")
    if w < 1 or h < 1 or w != round(w) or h != round(h):
        raise _fail(path, f"{where} image size w x h = {w} x {h}", "give the image width and height in whole pixels")
    if min(w, h) < MIN_IMAGE_SIDE:
        raise _fail(
            path,
            f"{where} image size w x h = {w:g} x {h:g} px is under the {MIN_IMAGE_SIDE} x {MIN_IMAGE_SIDE} minimum "
            "(training starts at 1/4 size)",
            f"use images at least {MIN_IMAGE_SIDE} px on each side",
        )
    if fx <= 0 or fy <= 0:
        raise _fail(path, f"{where} focal length fl_x, fl_y = {fx}, {fy}", "focal lengths are positive, in pixels")
    if max(fx, fy) > MAX_FOCAL_RATIO * max(w, h):
        raise _fail(
            path,
            f"{where} focal length fl_x, fl_y = {fx:g}, {fy:g} px is over {MAX_FOCAL_RATIO}x the image size",
            "give focal lengths in pixels (not mm or metres)",
        )


def _is_link_loop(path: Path) -> bool:
    try:
        path.stat()
    except OSError as err:
        return err.errno == errno.ELOOP
    return False


def _resolve_image(scene: Path, frame: dict, index: int, path: Path) -> Path:
    """The image file of frame ``index``: a regular file, or a path where none is (missing images are judged by the
    caller); a FIFO, a device, a socket or a folder there, or a path too long, is one line naming the frame."""
    fp = frame.get("file_path")
    if not isinstance(fp, str) or not fp.strip():
        raise _fail(
            path, f"frame {index} has no usable 'file_path' ({fp!r})", "set it to the image path relative to the scene"
        )
    where = f"{path}: frame {index} file_path {shown_path(fp)}"
    if _is_link_loop(scene / fp):  # pathlib's resolve() would raise RuntimeError("Symlink loop from ...")
        raise _fail(
            path,
            f"frame {index} file_path {fp}: {scene / fp} is a symbolic link that leads back to itself (a link loop)",
            "replace the link with the image file, or point it at one",
        )
    candidate = (scene / fp).resolve() if not Path(fp).is_absolute() else Path(fp)
    if regular_file(candidate, where, REPLACE_IMAGE):
        return candidate
    if "\\" in fp:  # written on Windows: its separators, where the file is there that way
        posix = scene / fp.replace("\\", "/")
        if regular_file(posix, where, REPLACE_IMAGE):
            return posix.resolve()
    if candidate.suffix == "":  # Blender-style extensionless paths
        for suffix in IMAGE_SUFFIXES + tuple(s.upper() for s in IMAGE_SUFFIXES):
            if regular_file(candidate.with_suffix(suffix), where, REPLACE_IMAGE):
                return candidate.with_suffix(suffix)
    return candidate


def near_match(missing: Path) -> Optional[Path]:
    """The file ``missing`` most likely meant: its name with other letter case, or its ``\\``-separated name read
    as a path (a file_path written on Windows) with other letter case; None when there is none."""
    names = [missing.name]
    if "\\" in missing.name:
        names.append(missing.name.replace("\\", "/"))
    for name in names:
        folder = (missing.parent / name).parent
        want = Path(name).name.lower()
        try:
            found = sorted(p for p in folder.iterdir() if p.name.lower() == want and p.name != Path(name).name)
        except OSError:
            continue
        if found:
            return found[0]
    return None


_WARNED_PADDED: set = set()
"""Transforms files already warned about zero bottom rows (a file is read for several splits)."""


def _bottom_row_zero(frame: dict) -> bool:
    try:
        return [float(v) for v in frame["transform_matrix"][3]] == [0.0] * 4
    except (KeyError, TypeError, ValueError, IndexError):
        return False


def _pose(frame: dict, index: int, path: Path) -> Tensor:
    try:
        mat = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
    except (KeyError, TypeError, ValueError):
        raise _fail(
            path, f"frame {index} has no numeric 'transform_matrix'", "give a 4x4 camera-to-world matrix"
        ) from None
    if mat.shape != (4, 4) or not torch.isfinite(mat).all():
        raise _fail(path, f"frame {index} 'transform_matrix' is not a finite 4x4", "give a 4x4 camera-to-world matrix")
    bottom = mat[3]
    if bool((bottom == 0).all()):
        mat[3, 3] = 1.0  # a 3x4 camera-to-world padded with zeros: read as meant (read_split warns once)
    elif float((bottom - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=mat.dtype)).abs().max()) > ROTATION_TOLERANCE:
        raise _fail(
            path,
            f"frame {index} 'transform_matrix' bottom row is {bottom.tolist()}, not [0, 0, 0, 1]",
            "give a rigid 4x4 camera-to-world (last row 0 0 0 1)",
        )
    rot = mat[:3, :3]
    error = float((rot.T @ rot - torch.eye(3, dtype=rot.dtype)).abs().max())
    if error > ROTATION_TOLERANCE or float(torch.linalg.det(rot)) <= 0:
        raise _fail(
            path,
            f"frame {index} 'transform_matrix' rotation block is not a rotation (|R^T R - I| = {error:.3g}, "
            f"det {float(torch.linalg.det(rot)):.3g})",
            "give a rigid camera-to-world (orthonormal rotation with det +1, no scale)",
        )
    return mat


def _check_distortion(k: dict, intr: List[float], path: Path, where: str) -> None:
    """The radial distortion maps the image one-to-one (increasing radius) with a corner scale in
    :data:`DISTORTION_SCALE_RANGE`; tangential terms are not judged (they are small in real lenses)."""
    radial = [k["k1"], k["k2"], k["k3"], k["k4"]]
    if not any(radial):
        return
    fx, fy, cx, cy, w, h = intr
    corner = max(math.hypot((x - cx) / fx, (y - cy) / fy) for x in (0.0, w) for y in (0.0, h))
    low, high = DISTORTION_SCALE_RANGE
    ru = np.linspace(0.0, corner / low, 4001)  # undistorted radii, far enough to reach the corner at scale `low`
    r2 = ru * ru
    rd = ru * (1.0 + r2 * (radial[0] + r2 * (radial[1] + r2 * (radial[2] + r2 * radial[3]))))
    reach = np.flatnonzero(rd >= corner)
    end = int(reach[0]) if reach.size else len(ru) - 1
    named = ", ".join(f"{key}={k[key]:g}" for key in ("k1", "k2", "k3", "k4") if k[key])
    fix = "check the coefficients (OpenCV order: k1 k2 p1 p2 k3) or remove them"
    if (np.diff(rd[: end + 1]) <= 0).any():
        turn = float(ru[int(np.flatnonzero(np.diff(rd[: end + 1]) <= 0)[0])])
        raise _fail(
            path,
            f"{where} distortion {named} folds the image (the radius turns back at {turn:.2f} of {corner:.2f})",
            fix,
        )
    scale = f"{corner / float(ru[end]):.2f}" if reach.size else f"under {low}"
    if not reach.size or not low <= corner / float(ru[end]) <= high:
        raise _fail(
            path, f"{where} distortion {named} scales the image corner by {scale} (real lenses: {low}-{high})", fix
        )


def _check_camera_spread(train: "SplitFrames") -> None:
    """Refuse training cameras all at one place, or one far out of the others (see :data:`MAX_CAMERA_SPREAD`):
    either would make the auto-scale degenerate (1e12, 1e-9) in silence."""
    centres = train.poses[:, :3, 3].double()
    # quantile, not median(): for an even count torch's median is the lower of the two middle values, which made
    # one of two cameras the centre and the other infinitely far out in median distances.
    mid = centres.quantile(0.5, dim=0)
    dist = (centres - mid).norm(dim=1)
    far = int(dist.argmax())
    if float(dist[far]) <= 1e-9 * max(1.0, float(mid.norm())):
        raise _fail(
            train.json_path,
            (f"all {len(dist)} training cameras are" if len(dist) > 1 else "the only training camera is")
            + f" at one position {[round(v, 6) for v in mid.tolist()]}",
            "3D reconstruction needs views from different positions: check the poses (a copied matrix?)",
        )
    median = float(dist.quantile(0.5))
    if float(dist[far]) > MAX_CAMERA_SPREAD * median:
        raise _fail(
            train.json_path,
            f"frame {far} ({train.images[far].name}) camera is {float(dist[far]):.3g} from the cameras' median "
            f"centre, over {MAX_CAMERA_SPREAD:g}x their median distance {median:.3g} (real captures: under 6x)",
            "fix its transform_matrix (units?) or remove the frame",
        )


@dataclass
class SplitFrames:
    """Raw (un-normalized) contents of one transforms json."""

    images: List[Path]
    poses: Float[Tensor, "N 4 4"]  # OpenGL camera-to-world, world units
    intrinsics: Float[Tensor, "N 6"]  # fx fy cx cy w h, pixels
    distortion: Float[Tensor, "N 6"]  # nerfstudio order k1 k2 k3 k4 p1 p2
    json_path: Path
    eval_truth: Literal["normal-light", "dark"] = "normal-light"
    """What the split's images are as eval truth: normal-light images, or the dark captures (the json's key)."""


EVAL_TRUTHS = ("normal-light", "dark")


def read_split(scene: Path, json_name: str) -> SplitFrames:
    """Parse one transforms json of ``scene`` (no normalization, no image checks)."""
    path = scene / json_name
    meta = load_transforms(path)
    images, poses, intr, dist = [], [], [], []
    padded = 0
    for i, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict):
            raise _fail(path, f"frame {i} is not an object", "each frame needs file_path and transform_matrix")
        images.append(_resolve_image(scene, frame, i, path))
        poses.append(_pose(frame, i, path))
        padded += int(_bottom_row_zero(frame))
        where = f"frame {i} ({frame.get('file_path')})"
        intr.append([_intrinsic(meta, frame, k, path, where) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")])
        _check_intrinsics(intr[-1], path, where)
        raw = {key: frame.get(key, meta.get(key)) for key in DISTORTION_KEYS}
        k = {key: 0.0 if v is None else _number(v, f"{where} '{key}'", path) for key, v in raw.items()}
        if not all(math.isfinite(v) for v in k.values()):
            raise _fail(path, f"{where} distortion {k} is not finite", "fix or remove the distortion coefficients")
        _check_distortion(k, intr[-1], path, where)
        dist.append(camera_utils.get_distortion_params(**k).tolist())
    if not images:
        raise _fail(path, "no frames", "list at least one frame")
    truth = meta.get("eval_truth", "normal-light")
    if truth not in EVAL_TRUTHS:
        raise _fail(path, f"'eval_truth' is {truth!r}", "give 'normal-light' or 'dark' (the images are dark captures)")
    if padded and path.resolve() not in _WARNED_PADDED:
        _WARNED_PADDED.add(path.resolve())
        CONSOLE.log(
            f"[naka-gs] warning: {path}: {padded} of {len(images)} frames have 'transform_matrix' bottom row "
            "0 0 0 0; read as 0 0 0 1 (a 3x4 camera-to-world padded with zeros)",
            markup=False,
        )
    return SplitFrames(
        images, torch.stack(poses), torch.tensor(intr, dtype=torch.float64), torch.tensor(dist), path, truth
    )


def normalization(train_poses: Float[Tensor, "N 4 4"], config: LowLightDataParserConfig) -> Tuple[Tensor, float]:
    """Scene normalization from the training poses: ``([3, 4] transform, scale)``, nerfstudio-style."""
    _, transform = camera_utils.auto_orient_and_center_poses(
        train_poses.float().clone(), method=config.orientation_method, center_method=config.center_method
    )
    oriented = transform @ train_poses.float()
    scale = 1.0
    if config.auto_scale_poses:
        scale = float(1.0 / torch.max(torch.abs(oriented[:, :3, 3])).clamp(min=1e-12))
    return transform, scale * config.scale_factor


def to_normalized_frame(
    points: Float[Tensor, "N 3"], transform: Float[Tensor, "3 4"], scale: float
) -> Float[Tensor, "N 3"]:
    """Map world points into the dataparser's normalized frame (same map as the camera centres)."""
    return (points @ transform[:, :3].T + transform[:, 3]) * scale


def auto_downscale(width: float, height: float) -> int:
    """Smallest power of two with the longer side at most :data:`MAX_AUTO_RESOLUTION`."""
    factor = 1
    while max(width, height) / factor > MAX_AUTO_RESOLUTION:
        factor *= 2
    return factor


class LowLightDataParser(DataParser):
    """Dataparser for ``lowlight-data`` scenes; see the module docstring."""

    config: LowLightDataParserConfig

    def _split_json(self, split: str) -> str:
        if split == "train":
            return "transforms_train.json"
        if split == "val" and (self.config.data / "transforms_val.json").exists():
            return "transforms_val.json"
        if split in ("val", "test"):
            return "transforms_test.json"
        raise ValueError(f"unknown split {split!r}; expected train, val or test")

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        scene = self.config.data
        found = input_stat(scene, "--data")
        if found is None or not stat.S_ISDIR(found.st_mode):
            raise LowLightDataError(
                f"{scene}: scene folder not found -- pass --data <folder with transforms_train.json>"
            )
        train = read_split(scene, "transforms_train.json")
        _check_camera_spread(train)
        frames = train if split == "train" else read_split(scene, self._split_json(split))
        transform, scale = normalization(train.poses, self.config)

        present = [p.exists() for p in frames.images]
        has_gt = all(present)
        if split == "train" or (any(present) and not has_gt):
            missing = [p for p, ok in zip(frames.images, present) if not ok]
            if missing:
                near = near_match(missing[0])
                hint = f"; did you mean {near}? (file names are case-sensitive)" if near is not None else ""
                raise _fail(
                    frames.json_path,
                    f"image {missing[0]} not found ({len(missing)} of {len(present)} missing){hint}",
                    "fix file_path or restore the images",
                )
        if not has_gt:
            CONSOLE.log(
                f"[naka-gs] {frames.json_path}: no ground-truth images for split '{split}' "
                f"({len(present)} poses load; metrics that need ground truth are skipped)",
                markup=False,
            )
        else:
            _check_sizes(frames)

        if self.config.downscale_factor is not None and self.config.downscale_factor < 1:
            raise LowLightDataError(
                f"lowlight-data --downscale-factor must be a whole number >= 1, got "
                f"{self.config.downscale_factor}: pass 1 (full resolution), 2, 4, ... or leave it out (automatic)"
            )
        factor = self.config.downscale_factor or auto_downscale(*frames.intrinsics[0, 4:6].tolist())
        side = int(frames.intrinsics[:, 4:6].min()) // factor  # the floor Cameras.rescale_output_resolution takes
        if side < MIN_IMAGE_SIDE:
            raise LowLightDataError(
                f"lowlight-data --downscale-factor {factor}: makes the images' shorter side "
                f"{side} px, under the {MIN_IMAGE_SIDE} px minimum (training starts at 1/4 size) -- pass a smaller "
                "factor or leave it out (automatic)"
            )
        images = frames.images
        if factor > 1 and has_gt:
            images = [downscaled_copy(p, factor) for p in frames.images]

        poses = transform.double() @ frames.poses
        poses[:, :3, 3] *= scale
        fx, fy, cx, cy, w, h = frames.intrinsics.unbind(-1)
        cameras = Cameras(
            camera_to_worlds=poses[:, :3, :4].float(),
            fx=fx.float()[:, None],
            fy=fy.float()[:, None],
            cx=cx.float()[:, None],
            cy=cy.float()[:, None],
            width=w.round().long()[:, None],
            height=h.round().long()[:, None],
            distortion_params=frames.distortion.float(),
            camera_type=CameraType.PERSPECTIVE,
        )
        if factor > 1:
            cameras.rescale_output_resolution(scaling_factor=1.0 / factor)
        box = 1.0 * self.config.scale_factor
        return DataparserOutputs(
            image_filenames=images,
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-box, -box, -box], [box, box, box]], dtype=torch.float32)),
            dataparser_transform=transform.float(),
            dataparser_scale=scale,
            metadata={
                "has_ground_truth": has_gt,
                "eval_truth": frames.eval_truth,
                "truth_note": f"{frames.json_path.name} says its images are the dark captures",
                "layout": "lowlight-data",
                "downscale_factor": factor,
                "scene": str(scene),
                "source_images": frames.images,  # the user's files (image_filenames may be downscaled copies)
            },
        )


def _check_sizes(frames: SplitFrames) -> None:
    """Every image opens and has the json's ``w x h`` (headers only: cheap)."""
    for path, intr in zip(frames.images, frames.intrinsics):
        size = _image_size(path)
        want = (int(round(intr[4].item())), int(round(intr[5].item())))
        if size != want:
            raise _fail(
                path,
                f"image is {size[0]}x{size[1]} but {frames.json_path.name} says {want[0]}x{want[1]}",
                "fix w/h in the json",
            )


def _image_size(path: Path) -> Tuple[int, int]:
    """``(width, height)`` from the header; files PIL cannot open (float32 RGB TIFFs, which the reader
    supports) are decoded in full, and an unreadable file raises the reader's one-line reason."""
    try:
        with open_regular(path, fix=REPLACE_IMAGE) as stream, Image.open(stream) as im:
            return im.size
    except OSError:
        arr = read_raw(path)
        return arr.shape[1], arr.shape[0]


def downscaled_copy(path: Path, factor: int) -> Path:
    """Path of ``path`` downscaled by ``factor`` (area filter) in the cache (``$NAKA_GS_CACHE``); made once.

    A cached copy that does not decode to the expected size (cut short, corrupted) is made again,
    with a warning; a new copy is written to a unique temporary name, read back whole (a full disk can
    cut it short while OpenCV reports success), and only then renamed.
    """
    digest = hashlib.sha1(f"{path.resolve()}|{path.stat().st_mtime_ns}|{path.stat().st_size}".encode()).hexdigest()[:16]
    folder = default_cache_dir() / "downscaled" / f"x{factor}"
    out = folder / f"{digest}_{path.stem}.png"
    width, height = _image_size(path)
    size = (int(width / factor), int(height / factor))  # floor, as Cameras.rescale_output_resolution does
    data, why = read_sealed(out)
    if data is not None:
        try:
            cached = read_raw(out)
        except ImageReadError:
            cached = None
        if cached is not None and (cached.shape[1], cached.shape[0]) == size:
            return out
        why = "is corrupt"
    if why:
        CONSOLE.log(f"[naka-gs] warning: cached copy {out} {why}; making it again", markup=False)
    raw = read_raw(path)
    folder.mkdir(parents=True, exist_ok=True)
    # INTER_AREA = box filter for integer factors; 16-bit sources stay 16-bit (dark detail lives there).
    small = cv2.resize(to_rgb01(raw, path), size, interpolation=cv2.INTER_AREA)
    scale, dtype = (255.0, np.uint8) if raw.dtype == np.uint8 else (65535.0, np.uint16)
    pixels = np.round(small[..., ::-1] * scale).astype(dtype)
    try:
        seal(write_image(out, pixels))
    except OSError as err:
        raise _fail(
            out,
            f"cannot write the downscaled copy of {path.name} ({err.strerror or 'disk full or not writable?'}; "
            "nothing was kept)",
            "free disk space there or set NAKA_GS_CACHE to a folder with room",
        ) from None
    return out


lowlight_dataparser = DataParserSpecification(
    config=LowLightDataParserConfig(),
    description="Low-light scenes: transforms_{train,val,test}.json with fl_x/fl_y/cx/cy, distortion, OpenGL c2w",
)
