"""``naka-gs-demo``: the README's main job on the embedded default scene (no downloads).

1. generates the default procedural low-light scene from ``configs/scenes/dark-noisy.yaml``
   (:mod:`naka_gs_plugin.sim`: rendered by our rasterizer, known normal-light truth);
2. enhances its training views as ``ns-train naka-gs`` does and scores input and enhanced images
   against the truth (PSNR, dB);
3. trains ``naka-gs`` on it (nerfstudio's own training loop, in-process, CPU or CUDA) and, as the
   baseline, the same model with enhancement off (plain splatfacto on the raw low-light images);
4. evaluates both on the held-out test views against their truth, as ``ns-eval`` would.

Outputs in ``--out``: ``side_by_side.png`` (rows: low-light input, enhanced, naka-gs render,
baseline render, truth; training views), ``test_renders.png`` (rows: naka-gs, baseline, truth;
test views), ``report.json``, the scene and the nerfstudio run folders
(``ns-viewer --load-config <out>/run/demo/naka-gs/naka-gs/config.yml``).
"""

from __future__ import annotations

import copy
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.scripts import run
from naka_gs_plugin.sheet import contact_sheet
from naka_gs_plugin.shipped import CONFIGS
from naka_gs_plugin.sim.generate import generate
from naka_gs_plugin.sim.spec import load_spec

DEFAULT_SPEC = CONFIGS / "scenes" / "dark-noisy.yaml"


@dataclass
class Demo:
    """Simulate a low-light scene, train naka-gs and the plain baseline on it, evaluate against the truth."""

    out: Path = Path("outputs/demo")
    spec: Path = DEFAULT_SPEC
    """Scene spec (configs/scenes/*.yaml)."""
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)
    steps: int = 500
    """Training steps per model (0: enhancement only)."""
    baseline: bool = True
    """Also train the same model with enhancement off on the same low-light images."""
    sheet_views: int = 4

    def main(self) -> dict:
        scene_dir = generate(load_spec(self.spec), self.out / "scene")
        names = sorted(p.name for p in (scene_dir / "train").iterdir())
        low = [torch.from_numpy(read_rgb(scene_dir / "train" / n)) for n in names]
        truth = [torch.from_numpy(read_rgb(scene_dir / "train_gt" / n)) for n in names]
        enhanced = Enhancer(self.enhance).enhance_images(low, description="Enhancing demo scene")
        report: Dict = {
            "scene": str(scene_dir),
            "train_views": len(names),
            "mean_input_brightness": float(np.mean([im.mean() for im in low])),
            "psnr_input_vs_truth_db": float(np.mean([psnr(a, t) for a, t in zip(low, truth)])),
            "psnr_enhanced_vs_truth_db": float(np.mean([psnr(e, t) for e, t in zip(enhanced, truth)])),
        }
        k = min(self.sheet_views, len(names))
        rows = [[im.numpy() for im in low[:k]], [im.numpy() for im in enhanced[:k]]]
        if self.steps > 0:
            runs = {"naka-gs": self.enhance}
            if self.baseline:
                runs["baseline"] = EnhanceConfig(method="none")
            test_rows = []
            for name, enhance in runs.items():
                metrics, train_renders, test_renders, test_truth = self._train_and_eval(scene_dir, name, enhance, k)
                report[name] = metrics
                rows.append(train_renders)
                test_rows.append(test_renders)
            Image.fromarray(contact_sheet(test_rows + [test_truth])).save(self.out / "test_renders.png")
        rows.append([t.numpy() for t in truth[:k]])
        Image.fromarray(contact_sheet(rows)).save(self.out / "side_by_side.png")
        (self.out / "report.json").write_text(json.dumps(report, indent=1))
        self._print(report)
        return report

    def _train_and_eval(self, scene_dir: Path, name: str, enhance: EnhanceConfig, k: int):
        # Imported here: nerfstudio's training stack is heavy and the enhancement step does not need it.
        from nerfstudio.scripts.train import main as train_main
        from nerfstudio.utils.eval_utils import eval_setup

        from naka_gs_plugin.config import naka_gs_method

        config = copy.deepcopy(naka_gs_method.config)
        config.data = scene_dir
        config.output_dir = self.out / "run"
        config.experiment_name = "demo"
        config.timestamp = name
        config.max_num_iterations = self.steps
        config.steps_per_save = self.steps
        config.vis = "tensorboard"
        config.viewer.quit_on_train_completion = True
        config.pipeline.datamanager.enhance = enhance
        config.pipeline.datamanager.dataparser.downscale_factor = 1
        config.pipeline.model.num_random = 20000
        config.pipeline.model.random_scale = 3.0  # covers the simulated scene's normalized extent
        # The demo's own run of an earlier call goes, as its other outputs are replaced (ns-train refuses to
        # train into a folder that holds a run).
        shutil.rmtree(config.get_base_dir(), ignore_errors=True)
        start = time.perf_counter()
        train_main(config)
        train_seconds = time.perf_counter() - start

        config_path = config.get_base_dir() / "config.yml"
        _, pipeline, _, _ = eval_setup(config_path, test_mode="test")
        metrics = pipeline.get_average_eval_image_metrics(get_std=False)
        pipeline.eval()  # get_average_eval_image_metrics leaves the pipeline in train mode
        with torch.no_grad():
            train_cams = pipeline.datamanager.train_dataset.cameras
            train_renders = [self._render(pipeline, train_cams[i : i + 1].to(pipeline.device)) for i in range(k)]
            test_renders, test_truth = [], []
            for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
                test_renders.append(self._render(pipeline, camera))
                image = batch["image"][..., :3].cpu()
                test_truth.append((image.float() / 255.0 if image.dtype == torch.uint8 else image).numpy())
        summary = {
            "train_steps": self.steps,
            "train_seconds": round(train_seconds, 1),
            "gaussians": int(pipeline.model.num_points),
            "test_psnr_db": float(metrics["psnr"]),
            "test_ssim": float(metrics["ssim"]),
            "test_lpips": float(metrics["lpips"]),
            "config": str(config_path),
        }
        return summary, train_renders, test_renders, test_truth

    @staticmethod
    def _render(pipeline, camera) -> np.ndarray:
        return pipeline.model.get_outputs_for_camera(camera)["rgb"].cpu().numpy()

    def _print(self, report: Dict) -> None:
        lines: List[str] = [
            f"{report['train_views']} dark training views (mean {report['mean_input_brightness']:.3f}): "
            f"PSNR vs truth {report['psnr_input_vs_truth_db']:.2f} dB as captured, "
            f"{report['psnr_enhanced_vs_truth_db']:.2f} dB after enhancement"
        ]
        for name in ("naka-gs", "baseline"):
            if name in report:
                r = report[name]
                lines.append(
                    f"{name:>8}: test PSNR {r['test_psnr_db']:.2f} dB, SSIM {r['test_ssim']:.3f}, LPIPS {r['test_lpips']:.3f} "
                    f"({r['train_steps']} steps in {r['train_seconds']:.0f} s, {r['gaussians']} Gaussians)"
                )
        lines.append(f"wrote {self.out}/side_by_side.png, test_renders.png, report.json")
        for line in lines:
            CONSOLE.print(f"[naka-gs demo] {line}", markup=False)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-demo`` (:func:`naka_gs_plugin.scripts.run`)."""
    run(Demo.main, Demo, args)


if __name__ == "__main__":
    entrypoint()
