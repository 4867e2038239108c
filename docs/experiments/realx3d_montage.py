"""RealX3D in 3D, one row per scene (docs/real-scenes.md, "RealX3D by eye"): the first row of each run's scene
sheet (enhanced training view | render at that pose | render halfway to the next view) with the scene's name,
stacked into one JPEG, and a Markdown table of the brightnesses (mean sRGB [0, 1]). From the repository root:
    .venv/bin/python docs/experiments/realx3d_montage.py docs/img/realx3d_3d_sheet.jpg \
        outputs/realx3d/*/naka-gs/ds4-gain/config.yml
"""

import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from benchmarks.scene_sheet import SceneSheet

output, configs = Path(sys.argv[1]), [Path(c) for c in sys.argv[2:]]
rows, table = (
    [],
    ["| scene | exposure `k` | enhanced (all views) | enhanced / render / novel (row view) |", "|---|---|---|---|"],
)
with tempfile.TemporaryDirectory() as tmp:
    for config in configs:
        scene = config.parents[2].name
        report = SceneSheet(load_config=config, views=1, output=Path(tmp) / f"{scene}.png", tile_width=256).main()
        image = Image.open(report["sheet"]).convert("RGB")
        draw = ImageDraw.Draw(image)
        font = ImageFont.load_default()
        _, _, right, bottom = draw.textbbox((4, 2), scene, font=font)
        draw.rectangle((0, 0, right + 4, bottom + 3), fill=(0, 0, 0))
        draw.text((4, 2), scene, fill=(255, 255, 255), font=font)
        rows.append(np.asarray(image))
        table.append(
            f"| {scene} | {report['exposure_value']:.2f} | {report['enhanced_mean_all_views']:.3f} | "
            f"{report['enhanced_mean']:.3f} / {report['render_mean']:.3f} / {report['novel_render_mean']:.3f} |"
        )
width = min(row.shape[1] for row in rows)
Image.fromarray(np.concatenate([row[:, :width] for row in rows])).save(output, quality=88)
print("\n".join(table))
