"""The scene layouts ``ns-train naka-gs`` reads: ``lowlight-data`` (the default), ``nerfstudio-data`` and ``colmap``.

``ns-train naka-gs [options] {lowlight-data,nerfstudio-data,colmap} [dataparser options]``, as nerfstudio's own
methods take a dataparser. The two nerfstudio layouts are nerfstudio's dataparsers with what naka-gs needs changed:

- **every view trains** (``--eval-mode all``): their images are all dark captures, so a held-out view would only
  be scored against a dark photo, never against normal-light truth. The outputs say so (``metadata["eval_truth"]
  = "dark"``): the datamanager labels such metrics ``vs_dark_*`` and ``ns-eval`` refuses them in one line.
- **downscaled copies go to the cache** (``$NAKA_GS_CACHE``, as lowlight-data's): nerfstudio's parsers read
  ``images_N`` folders inside the scene, and the colmap one offers to write them there.
- **seed points** are the pipeline's (``--pipeline.init``, with PPM): ``metadata["seed_frame"]`` names the layout's
  own points (nerfstudio-data's ``ply_file_path``, the colmap model) and the frame they live in; nerfstudio's
  ``load_3D_points`` is off.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Type, Union

import torch
import tyro
from jaxtyping import Float
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from torch import Tensor
from typing_extensions import Annotated

from naka_gs_plugin.data.lowlight_dataparser import (
    LowLightDataError,
    LowLightDataParserConfig,
    _image_size,
    auto_downscale,
    downscaled_copy,
    load_transforms,
)


def seed_frame(
    outputs: DataparserOutputs,
    transform: Float[Tensor, "3 4"],
    pose_scale: float,
    points: Optional[Path],
    points_share_frame: bool,
) -> Dict[str, Any]:
    """What seeding needs of a training split: image names, camera centres in the world frame of ``points``
    (the inverse of ``transform`` and ``pose_scale`` applied to the normalized centres), ``transform`` (world ->
    normalized, before the dataparser scale), the point file and whether it carries no cameras of its own but shares
    the poses' frame (nerfstudio-data's ply: its camera centres are then the poses')."""
    rot, shift = transform[:, :3].double(), transform[:, 3].double()
    normalized = outputs.cameras.camera_to_worlds[:, :3, 3].double()
    centres = (normalized / pose_scale - shift) @ rot  # R^T (y / s - t), row vectors
    return {
        "names": [Path(p).name for p in outputs.metadata["source_images"]],
        "centres": centres.numpy(),
        "transform": transform.double().numpy(),
        "scale": float(outputs.dataparser_scale),
        "points": points,
        "points_share_frame": points_share_frame,
    }


def _cached_images(images: List[Path], factor: int, scene: Path) -> List[Path]:
    """``images`` downscaled by ``factor`` into the cache (the scene is never written to); each must exist."""
    missing = [p for p in images if not Path(p).is_file()]
    if missing:
        raise LowLightDataError(
            f"{missing[0]}: image not found ({len(missing)} of {len(images)} missing) -- restore it or fix {scene}'s "
            "camera list"
        )
    return [downscaled_copy(Path(p), factor) for p in images] if factor > 1 else list(images)


def _refuse_side_files(has_side_files: bool, factor: int, layout: str) -> None:
    """Masks and depths would need downscaled copies in the scene (``masks_N``): refused in one line."""
    if factor > 1 and has_side_files:
        raise LowLightDataError(
            f"{layout}: masks or depth maps with --downscale-factor {factor} would need downscaled copies written "
            "into the scene -- pass --downscale-factor 1 (full size)"
        )


def _layout_metadata(outputs: DataparserOutputs, layout: str, scene: Path, factor: int, sources: List[Path]) -> None:
    outputs.metadata.update(
        has_ground_truth=True,
        eval_truth="dark",
        truth_note=f"{layout} layout: its eval images are the dark captures",
        layout=layout,
        downscale_factor=factor,
        scene=str(scene),
        source_images=sources,
    )


def _scene_folder(data: Path, layout: str, needs: str) -> None:
    if not Path(data).exists():
        raise LowLightDataError(f"{data}: scene not found -- pass --data <{layout} scene folder with {needs}>")


@dataclass
class NerfstudioLayoutConfig(NerfstudioDataParserConfig):
    """nerfstudio-data (``transforms.json``, e.g. ``ns-process-data``'s output): every view trains, downscaled copies
    in the cache, seed points from ``ply_file_path``."""

    _target: Type = field(default_factory=lambda: NerfstudioLayout)
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "all"
    """all: every view trains (the eval images are dark captures, not normal-light truth); interval, fraction or
    filename hold views out as nerfstudio does, and their metrics are labelled vs_dark_*."""
    load_3D_points: tyro.conf.Suppress[bool] = False
    """Off: the pipeline seeds from ``ply_file_path`` itself (``--pipeline.init``, aligned and cleaned by PPM)."""


class NerfstudioLayout(Nerfstudio):
    """nerfstudio's parser, reading full-size images (downscaled into the cache) and labelling its eval images."""

    config: NerfstudioLayoutConfig

    def _get_fname(self, filepath: Path, data_dir: Path, downsample_folder_prefix: str = "images_") -> Path:
        """The file itself, never an ``images_N`` copy; the first call picks the downscale (lowlight-data's rule)."""
        if self.downscale_factor is None:
            self.downscale_factor = self.config.downscale_factor or auto_downscale(*_image_size(data_dir / filepath))
        return data_dir / filepath

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        path = data if data.suffix == ".json" else data / "transforms.json"
        _scene_folder(data, "nerfstudio-data", "transforms.json")
        if not path.is_file():
            raise LowLightDataError(f"{path}: not found -- a nerfstudio-data scene needs transforms.json")
        meta = load_transforms(path)
        scene = path.parent
        outputs = super()._generate_dataparser_outputs(split)
        factor = int(self.downscale_factor or 1)
        _refuse_side_files(
            bool(outputs.mask_filenames or outputs.metadata.get("depth_filenames")), factor, "nerfstudio-data"
        )
        sources = list(outputs.image_filenames)
        outputs.image_filenames = _cached_images(sources, factor, scene)
        _layout_metadata(outputs, "nerfstudio-data", scene, factor, sources)
        # nerfstudio maps the ply (which lives in transforms.json's frame) with the transform *before*
        # applied_transform (the COLMAP -> transforms.json change ns-process-data made): so does the seed.
        applied = meta.get("applied_transform")
        if applied is None and (data / "colmap/sparse/0").exists():
            applied = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]
        transform = outputs.dataparser_transform.double()
        if applied is not None:
            full = torch.cat([torch.tensor(applied, dtype=torch.float64), torch.tensor([[0.0, 0.0, 0.0, 1.0]])])
            transform = (torch.cat([transform, torch.tensor([[0.0, 0.0, 0.0, 1.0]])]) @ torch.linalg.inv(full))[:3]
        ply = meta.get("ply_file_path")
        points = scene / ply if isinstance(ply, str) and ply else None
        pose_scale = outputs.dataparser_scale / float(meta.get("applied_scale", 1.0))
        outputs.metadata["seed_frame"] = seed_frame(outputs, transform, pose_scale, points, True)
        return outputs


@dataclass
class ColmapLayoutConfig(ColmapDataParserConfig):
    """colmap (``images/`` + ``sparse/0``): every view trains, downscaled copies in the cache, seed points from the
    model's points3D."""

    _target: Type = field(default_factory=lambda: ColmapLayout)
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "all"
    """all: every view trains (the eval images are dark captures, not normal-light truth); interval, fraction or
    filename hold views out as nerfstudio does, and their metrics are labelled vs_dark_*."""
    colmap_path: Path = Path("sparse/0")
    """The COLMAP model, relative to the scene (nerfstudio's ns-process-data writes ``colmap/sparse/0``)."""
    load_3D_points: tyro.conf.Suppress[bool] = False
    """Off: the pipeline seeds from the model itself (``--pipeline.init``, aligned and cleaned by PPM)."""
    downscale_rounding_mode: tyro.conf.Suppress[Literal["floor", "round", "ceil"]] = "floor"
    """Floor, as the cached copies are cut."""


class ColmapLayout(ColmapDataParser):
    """nerfstudio's COLMAP parser, downscaling into the cache instead of ``images_N`` beside the scene's images."""

    config: ColmapLayoutConfig

    def _setup_downscale_factor(self, image_filenames: List[Path], mask_filenames: List[Path], depth_filenames):
        if self._downscale_factor is None:
            self._downscale_factor = self.config.downscale_factor or auto_downscale(*_image_size(image_filenames[0]))
        factor = int(self._downscale_factor)
        _refuse_side_files(bool(mask_filenames or depth_filenames), factor, "colmap")
        images = _cached_images(image_filenames, factor, Path(self.config.data))
        self._source_of = {str(c): s for c, s in zip(images, image_filenames)}
        return images, mask_filenames, depth_filenames, factor

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        _scene_folder(data, "colmap", f"images/ and {self.config.colmap_path}/")
        model = data / self.config.colmap_path
        if not (model / "cameras.bin").is_file() and not (model / "cameras.txt").is_file():
            raise LowLightDataError(
                f"{model}: no COLMAP model (cameras.bin|txt, images.bin|txt) -- pass --colmap-path <the model folder, "
                "relative to the scene>"
            )
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        sources = [self._source_of[str(p)] for p in outputs.image_filenames]
        _layout_metadata(outputs, "colmap", data, int(self._downscale_factor), sources)
        outputs.metadata["seed_frame"] = seed_frame(
            outputs,
            outputs.dataparser_transform,
            outputs.dataparser_scale,
            model if _has_points(model) else None,
            False,
        )
        return outputs


def _has_points(model: Path) -> bool:
    """Whether the COLMAP model holds a point (else seeding triangulates): a binary points3D with a non-zero count,
    or a text one with a line that is not a comment."""
    binary, text = model / "points3D.bin", model / "points3D.txt"
    if binary.is_file():
        with open(binary, "rb") as stream:
            return int.from_bytes(stream.read(8), "little") > 0
    if text.is_file():
        with open(text, encoding="utf-8", errors="replace") as stream:
            return any(line.strip() and not line.startswith("#") for line in stream)
    return False


LayoutConfig = tyro.conf.OmitSubcommandPrefixes[
    Union[
        Annotated[LowLightDataParserConfig, tyro.conf.subcommand("lowlight-data", prefix_name=False)],
        Annotated[NerfstudioLayoutConfig, tyro.conf.subcommand("nerfstudio-data", prefix_name=False)],
        Annotated[ColmapLayoutConfig, tyro.conf.subcommand("colmap", prefix_name=False)],
    ]
]
"""The ``ns-train naka-gs`` dataparser subcommands (lowlight-data when none is named)."""
