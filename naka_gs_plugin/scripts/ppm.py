"""``naka-gs-ppm IN --out OUT.ply``: clean a point cloud with PPM, as ``ns-train naka-gs`` does before seeding.

``IN`` is a .ply, a COLMAP sparse model folder, a VGGT output folder, or a lowlight-data scene
folder (its own point source is used, as ``--pipeline.init.points auto`` would, without the
triangulation fallback, which needs the training pipeline). With ``--scene`` (implied when ``IN``
is a scene) the points are aligned to the scene's training cameras and normalized to its training
frame, exactly as for training; without it they stay in the source frame and the voxel size and
tau are in the source's units. Writes OUT.ply (binary, float32 xyz + uchar rgb when the source
has colours) and a JSON summary (counts after each stage and pruning iteration, alignment
residual, timings).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Optional, Sequence

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.data.safe_io import atomic_write_bytes
from naka_gs_plugin.errors import UserError
from naka_gs_plugin.points.seeding import PointInitConfig, PPMSettings, TrainingFrame, describe, prepare_points
from naka_gs_plugin.points.sources import PointSourceError, find_scene_source, load_points, source_files, write_ply
from naka_gs_plugin.scripts import run


class PpmOutputError(UserError, ValueError):
    """The output cannot be written (read-only place, a file in the way, an input); one line."""


@dataclass(kw_only=True)
class Ppm(PPMSettings):
    """Clean a point cloud with Naka-GS's PPM (voxel pooling + progressive pruning)."""

    input: tyro.conf.Positional[Path]
    """Point source: .ply, COLMAP model folder, VGGT output folder, or a lowlight-data scene folder."""
    out: Path
    """Output PLY."""
    summary: Optional[Path] = None
    """JSON summary path (default: OUT with .json)."""
    scene: Optional[Path] = None
    """lowlight-data scene whose training frame the points are aligned and normalized to."""

    def main(self) -> dict:
        source = self.input
        scene = self.scene
        if source.is_dir() and (source / "transforms_train.json").is_file():
            scene = scene or source
            found = find_scene_source(source)
            if found is None:
                raise PointSourceError(
                    f"{source}: the scene has no point source (sparse/0, sparse, colmap_sparse/0, points.ply) -- "
                    "pass a point file, or train with --pipeline.init.points auto to triangulate"
                )
            source = found
        inputs = source_files(source) + ([scene / "transforms_train.json"] if scene is not None else [])
        for out in (self.out, self.summary or self.out.with_suffix(".json")):
            if out.resolve() in {p.resolve() for p in inputs}:
                raise PpmOutputError(f"--out {out}: is an input of this run -- choose another output path")
        cloud = load_points(source)
        frame = TrainingFrame.from_scene(scene) if scene is not None else None
        if frame is None:
            CONSOLE.log(
                "[naka-gs] no --scene: points stay in the source frame (no alignment); "
                f"voxel {self.voxel_size} and tau0 {self.tau0} are in the source's units",
                markup=False,
            )
        init = PointInitConfig(points=str(source), **{f.name: getattr(self, f.name) for f in fields(PPMSettings)})
        xyz, rgb, summary = prepare_points(cloud, frame, init)
        summary["scene"] = str(scene) if scene is not None else None
        summary["output"] = str(self.out)
        summary_path = self.summary or self.out.with_suffix(".json")
        option, written = "--out", self.out
        try:
            write_ply(self.out, xyz, rgb)
            option, written = "--summary", summary_path
            summary_path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(summary_path, json.dumps(summary, indent=1).encode())
        except OSError as err:
            in_the_way = isinstance(err, (FileExistsError, NotADirectoryError))
            reason = f"{written.parent} is not a folder" if in_the_way else (err.strerror or str(err))
            raise PpmOutputError(
                f"{option} {written}: cannot write it ({reason}) -- choose a writable {option}"
            ) from None
        CONSOLE.log(f"[naka-gs] {describe(summary)}; wrote {self.out} and {summary_path}", markup=False)
        return summary


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-ppm`` (:func:`naka_gs_plugin.scripts.run`)."""
    run(Ppm.main, Ppm, args, config=(tyro.conf.FlagConversionOff,))  # --ppm True/False, as ns-train


if __name__ == "__main__":
    entrypoint()
