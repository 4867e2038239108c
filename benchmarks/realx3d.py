"""``python -m benchmarks.realx3d benchmarks/configs/realx3d.yaml``: RealX3D as a user would run it.

1. calibrates the camera once on the calibration pairs the file names (``naka-gs-calibrate``), unless the profile
   is already there;
2. trains every scene with ``ns-train naka-gs --pipeline.datamanager.enhance.profile PROFILE`` (plus the file's
   ``settings``), each in its own process, skipping scenes whose run finished;
3. renders every test view in the challenge's layout, the layout of ``transforms_test.json``: ``challenge/<Scene>/
   <file name of the frame>`` at the json's full resolution, 8-bit, JPEG quality 95 (as the reference code saves its
   test renders), whether or not the scene has truth;
4. scores the scenes that have test truth with ``ns-eval`` (``eval/<Scene>.json``).

Outputs in ``--out``: ``profile.json`` (+ its sheet), ``runs/``, ``challenge/``, ``eval/``, ``results.json`` (timings,
scores). Re-running resumes.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np
import tyro
import yaml
from nerfstudio.utils.rich_utils import CONSOLE

from benchmarks.harness import timed
from naka_gs_plugin.data.lowlight_dataparser import read_split
from naka_gs_plugin.data.safe_io import atomic_write_bytes

JPEG_QUALITY = 95


def _log(message: str) -> None:
    CONSOLE.print(f"[naka-gs realx3d] {message}", markup=False)


def _bin(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def render_test_views(config_yml: Path, out: Path) -> int:
    """Render every frame of the run's scene's ``transforms_test.json`` at the json's resolution into ``out``,
    named as the frame's file; returns the count. (``ns-render dataset --split test`` renders the same poses, but at
    the training resolution and under its own names.)"""
    import cv2
    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config_yml, test_mode="inference")
    parser = dataclasses.replace(pipeline.datamanager.config.dataparser, downscale_factor=1).setup()
    test = parser.get_dataparser_outputs("test")
    names = [Path(p).name for p in test.metadata["source_images"]]
    out.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        for i, name in enumerate(names):
            camera = test.cameras[i : i + 1].to(pipeline.device)
            rgb = pipeline.model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1).cpu().numpy()
            bgr = (rgb[..., ::-1] * 255.0 + 0.5).astype(np.uint8)
            ok, data = cv2.imencode(Path(name).suffix or ".png", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError(f"could not encode {name}")
            atomic_write_bytes(out / name, data.tobytes())
    return len(names)


class RealX3DSpecError(ValueError):
    """A benchmark file that cannot be run; one line naming the file and the fix."""


def load_spec(path: Path) -> Dict[str, Any]:
    """The benchmark file: ``calibrate`` (the pairs), ``scenes`` (name -> lowlight-data scene) and optional
    ``settings`` (``ns-train`` options without their dashes); a missing key or folder is one line."""
    try:
        spec = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise RealX3DSpecError(f"{path}: cannot read it ({err}) -- pass benchmarks/configs/realx3d.yaml") from None
    if not isinstance(spec, dict) or "calibrate" not in spec or not isinstance(spec.get("scenes"), dict):
        raise RealX3DSpecError(f"{path}: needs 'calibrate: PAIRS' and 'scenes: {{name: scene folder}}'")
    if not isinstance(spec.setdefault("settings", {}), dict):
        raise RealX3DSpecError(f"{path}: 'settings' must map ns-train options to values")
    return spec


@dataclass
class RealX3D:
    """Calibrate on the calibration pairs, train every scene with the profile, render the challenge's layout."""

    config: tyro.conf.Positional[Path] = Path("benchmarks/configs/realx3d.yaml")
    out: Path = Path("outputs/bench/realx3d")
    only: Tuple[str, ...] = ()
    """Only these scenes (names as in the file)."""

    def main(self) -> Dict[str, Any]:
        spec = load_spec(self.config)
        self.out.mkdir(parents=True, exist_ok=True)
        results_file = self.out / "results.json"
        results = json.loads(results_file.read_text()) if results_file.exists() else {"scenes": {}}
        profile = self.out / "profile.json"
        if not profile.exists():
            cmd = [_bin("naka-gs-calibrate"), spec["calibrate"], "--out", str(profile)]
            wall, rss = timed(cmd, None, self.out / "calibrate.log")
            results["calibration"] = {"pairs": spec["calibrate"], "wall_s": wall, "peak_rss_gb": round(rss, 2)}
            _log(f"calibrated on {spec['calibrate']} in {wall:.0f} s (peak {rss:.1f} GB): {profile}")
        settings = [str(a) for key, value in spec["settings"].items() for a in (f"--{key}", value)]
        for name, scene in spec["scenes"].items():
            if self.only and name not in self.only:
                continue
            record = results["scenes"].setdefault(name, {})
            config_yml = self.out / "runs" / name / "naka-gs" / "profile" / "config.yml"
            if "train_s" not in record:
                cmd = [
                    _bin("ns-train"), "naka-gs", "--data", scene, "--output-dir", str(self.out / "runs"),
                    "--experiment-name", name, "--timestamp", "profile", "--vis", "tensorboard",
                    "--viewer.quit-on-train-completion", "True",
                    "--pipeline.datamanager.enhance.profile", str(profile), *settings,
                ]  # fmt: skip
                log = self.out / "logs" / f"{name}.train.log"
                log.parent.mkdir(parents=True, exist_ok=True)
                wall, rss = timed(cmd, None, log)
                record.update(train_s=wall, peak_rss_gb=round(rss, 2))
            start = time.perf_counter()
            record["renders"] = render_test_views(config_yml, self.out / "challenge" / name)
            record["render_s"] = round(time.perf_counter() - start, 1)
            if all(p.exists() for p in read_split(Path(scene), "transforms_test.json").images):
                eval_json = self.out / "eval" / f"{name}.json"
                eval_json.parent.mkdir(parents=True, exist_ok=True)
                subprocess.run(
                    [_bin("ns-eval"), "--load-config", str(config_yml), "--output-path", str(eval_json)], check=True
                )
                record["scores"] = json.loads(eval_json.read_text())["results"]
            results_file.write_text(json.dumps(results, indent=1))
            _log(f"{name}: {json.dumps(record)}")
        return results


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    tyro.cli(RealX3D, args=args).main()


if __name__ == "__main__":
    entrypoint()
