"""``naka-gs-scene-sheet --load-config RUN/config.yml``: a trained scene by eye, with brightnesses.

The sheet's columns and the numbers are described in :mod:`naka_gs_plugin.bench.scene_sheet`. Run from the
directory ``ns-train`` ran in (the config's paths are relative to it, as for ``ns-eval``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.bench.scene_sheet import (
    COLUMNS,
    interpolate_pose,
    mean_brightness,
    render_at,
    sheet_views,
    trained_pose,
)
from naka_gs_plugin.enhance.stages import to_float01
from naka_gs_plugin.sheet import contact_sheet


@dataclass
class SceneSheet:
    """Sheet and brightness JSON of a trained ``naka-gs`` run (see the module docstring)."""

    load_config: Path
    """The run's config.yml, as written by ``ns-train naka-gs``."""
    views: int = 3
    """Rows: training views, evenly spaced over the training set."""
    output: Optional[Path] = None
    """Sheet PNG; the JSON goes beside it with suffix .json. Default: scene_sheet.png in the run folder."""
    tile_width: int = 384
    """Width in pixels of each picture on the sheet (never enlarged)."""

    def main(self) -> Dict:
        """Write the sheet and the JSON; return the JSON's contents."""
        if not self.load_config.is_file():
            raise FileNotFoundError(
                f"--load-config {self.load_config} is not a file -- pass the config.yml that ns-train wrote "
                "(outputs/SCENE/naka-gs/TIMESTAMP/config.yml)"
            )
        if self.views < 1:
            raise ValueError(f"--views must be >= 1, got {self.views} -- use e.g. --views 3")
        # Heavy: nerfstudio's method registry imports every model.
        from nerfstudio.utils.eval_utils import eval_setup

        _, pipeline, _, step = eval_setup(self.load_config, test_mode="test")
        datamanager, model = pipeline.datamanager, pipeline.model
        # Loading the training images enhances them (from the cache when ns-train filled it) and, for
        # distorted captures, rewrites the cameras' intrinsics to the undistorted images': load first.
        train = [to_float01(data["image"]).cpu() for data in datamanager.cached_train]
        cameras = datamanager.train_dataset.cameras
        if len(train) < 2:
            raise ValueError(
                f"--load-config {self.load_config}: the scene has {len(train)} training view(s), "
                "a novel pose between two needs at least 2 -- train on a scene with more views"
            )

        rows, records = [], []
        for i in sheet_views(len(train), self.views):
            j = i + 1 if i + 1 < len(train) else i - 1
            c2w_i, c2w_j = trained_pose(model, cameras, i), trained_pose(model, cameras, j)
            render = render_at(model, cameras, i, c2w_i)
            novel = render_at(model, cameras, i, interpolate_pose(c2w_i, c2w_j, 0.5))
            rows.append([train[i].numpy(), render.numpy(), novel.numpy()])
            records.append(
                {
                    "view": i,
                    "image": datamanager.train_dataset.image_filenames[i].name,
                    "novel_towards_view": j,
                    "enhanced_mean": mean_brightness([train[i]]),
                    "render_mean": mean_brightness([render]),
                    "novel_render_mean": mean_brightness([novel]),
                }
            )

        output = self.output or self.load_config.parent / "scene_sheet.png"
        output.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(contact_sheet(rows, max_width=self.tile_width)).save(output)
        report = {
            "config": str(self.load_config),
            "step": step,
            "train_views": len(train),
            "enhanced_mean_all_views": mean_brightness(train),
            "exposure_curve": datamanager.enhancer.last_run.get("exposure_curve"),
            "exposure_value": datamanager.enhancer.last_run.get("exposure_value"),
            "enhanced_mean": float(np.mean([r["enhanced_mean"] for r in records])),
            "render_mean": float(np.mean([r["render_mean"] for r in records])),
            "novel_render_mean": float(np.mean([r["novel_render_mean"] for r in records])),
            "columns": list(COLUMNS),
            "rows": records,
            "sheet": str(output),
        }
        output.with_suffix(".json").write_text(json.dumps(report, indent=1))
        curve, value = report["exposure_curve"], report["exposure_value"]
        CONSOLE.print(
            f"[naka-gs scene-sheet] {len(train)} training views, enhanced mean {report['enhanced_mean_all_views']:.3f}"
            + (f" (exposure {curve} {value:.3f})" if value is not None else "")
            + f"; sheet views: enhanced {report['enhanced_mean']:.3f}, render {report['render_mean']:.3f}, "
            f"novel render {report['novel_render_mean']:.3f}; wrote {output} (columns: {' | '.join(COLUMNS)}) "
            f"and {output.with_suffix('.json')}",
            markup=False,
        )
        return report


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-scene-sheet``; bad input prints one line."""
    sheet = tyro.cli(SceneSheet, args=args)
    try:
        sheet.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"naka-gs-scene-sheet: {err}") from None


if __name__ == "__main__":
    entrypoint()
