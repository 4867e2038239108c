"""Write a simulated ``lowlight-data`` scene from a :class:`~naka_gs_plugin.sim.spec.SceneSpec`.

Output folder::

    train/NNNN.png|.jpg     degraded training images (encoding: see naka_gs_plugin.sim.effects)
    train_gt/NNNN.png       normal-light truth of the training views
    test/NNNN.png           normal-light truth of the test views
    transforms_train.json   fl_x fl_y cx cy w h (+ distortion for captures), frames: file_path,
    transforms_test.json    transform_matrix (OpenGL camera-to-world)
    points.ply              procedural only: dense noisy point cloud in a sim3-offset frame
    points_cameras.json     procedural only: train image file name -> camera centre in that frame
    sim_manifest.json       spec, seeds, the applied effects in order, encoding, per-view values

Randomness: ``seed`` drives only the sensor noise (one stream per view); ``scene_seed`` drives
textures, lamp positions, exposure jitter and the point cloud. Same spec and seeds -> identical bytes.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Dict, Optional, Union

import numpy as np
import torch
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.progress import StageProgress
from naka_gs_plugin.sim import points as pc
from naka_gs_plugin.sim.capture import CaptureScene
from naka_gs_plugin.sim.effects import encode, image_suffix, sensor, write_image
from naka_gs_plugin.sim.procedural import ProceduralScene
from naka_gs_plugin.sim.spec import (
    EFFECT_NAMES,
    EFFECT_ORDER,
    ExposureJitter,
    LightSources,
    Noise,
    ProceduralSource,
    Quantize,
    Response,
    SceneSpec,
    to_jsonable,
)
from naka_gs_plugin.sim.views import View, lamp_image, place_lamps

Scene = Union[ProceduralScene, CaptureScene]

_STREAM_JITTER, _STREAM_LAMPS, _STREAM_POINTS = 1, 2, 3


def build_scene(spec: SceneSpec) -> Scene:
    """The spec's source: Gaussians + rig (procedural) or the capture's views."""
    if isinstance(spec.source, ProceduralSource):
        return ProceduralScene(spec.source, spec.scene_seed)
    return CaptureScene(spec.source, spec.path)


def noise_generator(seed: int, view: View) -> torch.Generator:
    """Independent, reproducible noise stream of one view."""
    split = 0 if view.split == "train" else 1
    state = np.random.SeedSequence([seed, split, view.index]).generate_state(1)[0]
    return torch.Generator().manual_seed(int(state))


def encoding_of(spec: SceneSpec) -> Dict[str, Any]:
    """How the training images store values (recorded in the manifest)."""
    response = spec.effect(Response)
    curve = (
        "linear" if response is None else (response.curve if response.curve == "srgb" else f"gamma {response.gamma}")
    )
    return {
        "values": curve,
        "bit_depth": 8 if spec.effect(Quantize) else 16,
        "train_format": image_suffix(spec.effects, ground_truth=False)[1:],
        "ground_truth": "same response and bit depth as train, PNG, no degradation",
    }


def generate(spec: SceneSpec, out: Path, seed: Optional[int] = None) -> Path:
    """Write the scene of ``spec`` to ``out`` (``seed`` overrides the spec's noise seed)."""
    if seed is not None:
        spec = SceneSpec(spec.name, spec.source, spec.effects, seed, spec.scene_seed, spec.path)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene = build_scene(spec)
    train_views = [v for v in scene.views if v.split == "train"]

    jitter = np.ones(len(scene.views))
    if (j := spec.effect(ExposureJitter)) is not None:
        jitter = 2.0 ** np.random.default_rng([spec.scene_seed, _STREAM_JITTER]).normal(0.0, j.stops, len(scene.views))
    lamps_cfg, lamps = spec.effect(LightSources), np.zeros((0, 3))
    if lamps_cfg is not None:
        centre, radius = scene.lamp_region
        lamps = place_lamps(np.random.default_rng([spec.scene_seed, _STREAM_LAMPS]), lamps_cfg.count, centre, radius)

    frames: Dict[str, list] = {"train": [], "test": []}
    per_view = []
    suffix = image_suffix(spec.effects, ground_truth=False)
    with StageProgress() as progress:
        task = progress.add_task(f"naka-gs-sim {spec.name}", total=len(scene.views))
        for k, view in enumerate(scene.views):
            clean = scene.clean(view)
            truth = encode(clean.clamp(0.0, 1.0), spec.effects)
            if view.split == "train":
                lamp = lamp_image(view, lamps, lamps_cfg.intensity, lamps_cfg.radius) if lamps_cfg else None
                generator = noise_generator(spec.seed, view) if spec.effect(Noise) else None
                recorded = sensor(clean, spec.effects, float(jitter[k]), lamp, generator)
                write_image(out / "train" / f"{view.name}{suffix}", encode(recorded, spec.effects), spec.effects, False)
                write_image(out / "train_gt" / f"{view.name}.png", truth, spec.effects, True)
                file_path = f"train/{view.name}{suffix}"
                per_view.append(
                    {
                        "file_path": file_path,
                        "exposure_multiplier": float(jitter[k]),
                        "saturated_fraction": float((recorded >= 1.0).any(-1).double().mean()),
                        "source_image": view.origin,
                    }
                )
            else:
                write_image(out / "test" / f"{view.name}.png", truth, spec.effects, True)
                file_path = f"test/{view.name}.png"
            frames[view.split].append({"file_path": file_path, "transform_matrix": view.c2w.tolist()})
            progress.advance(task)
    for split, items in frames.items():
        body = {**{k: float(v) for k, v in scene.intrinsics().items()}, "frames": items}
        (out / f"transforms_{split}.json").write_text(json.dumps(body, indent=1))

    manifest: Dict[str, Any] = {
        "generator": "naka-gs-sim",
        "spec_file": str(spec.path.resolve()) if spec.path else None,
        "spec_sha256": hashlib.sha256(spec.path.read_bytes()).hexdigest()
        if spec.path and spec.path.is_file()
        else None,
        "spec": spec.to_dict(),
        "seed": spec.seed,
        "scene_seed": spec.scene_seed,
        "effects_applied": [{"name": EFFECT_NAMES[type(e)], **e.__dict__} for e in spec.effects],
        "effects_not_applied": [n for n in EFFECT_ORDER if n not in {EFFECT_NAMES[type(e)] for e in spec.effects}],
        "pipeline_order": list(EFFECT_ORDER),
        "encoding": encoding_of(spec),
        "lamps_world": lamps.tolist(),
        "train_views": per_view,
    }
    if isinstance(scene, ProceduralScene):
        manifest["points"] = _write_points(spec, scene, train_views, out)
    (out / "sim_manifest.json").write_text(json.dumps(to_jsonable(manifest), indent=1))
    CONSOLE.log(f"naka-gs-sim: wrote {spec.name} to {out}", markup=False)
    return out


def _write_points(spec: SceneSpec, scene: ProceduralScene, train_views: list, out: Path) -> Dict[str, Any]:
    cfg = spec.source.points
    rng = np.random.default_rng([spec.scene_seed, _STREAM_POINTS])
    xyz, rgb = pc.sample_point_cloud(cfg, scene.points, scene.colors, rng)
    m = pc.sim3_matrix(cfg.sim3)
    pc.write_ply(out / "points.ply", pc.apply_sim3(m, xyz), rgb)
    suffix = image_suffix(spec.effects, ground_truth=False)
    centres = pc.camera_centres(m, {f"{v.name}{suffix}": v.c2w for v in train_views})
    (out / "points_cameras.json").write_text(json.dumps(centres, indent=1))
    return {
        "file": "points.ply",
        "cameras": "points_cameras.json",
        "n_points": len(xyz),
        "sim3": {**cfg.sim3.__dict__, "matrix": m.tolist()},
        "sim3_maps": "transforms_*.json world frame -> points.ply frame: x' = scale * R @ x + translation",
    }
