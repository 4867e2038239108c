"""One scene's training views for the 2D probes (``tone/floor_2d.py``, ``realx3d_colour/wide_chroma_2d.py``):
the dark captures at the training resolution, their enhancement up to the exposure step, and the normal-light
photos to score them against. BlueHawaii: the shipped weights and its references (``transforms_reference.json``);
a LOM scene: its hold-out weights ``outputs/correction-loo/SCENE/best.pt`` and its ``high/`` photos.
"""

import sys
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import torch

from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, read_split
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.enhance.stages import to_float01


def scene_views(
    scene: str, transform: Optional[Callable[[List[torch.Tensor]], List[torch.Tensor]]] = None, **enhance
) -> Tuple[List[torch.Tensor], List[torch.Tensor], List[Path], List[str]]:
    """``(captures, enhanced, references, names)`` of ``scene``'s training views; sRGB ``[H, W, 3]`` in [0, 1].
    ``transform``: applied to the captures before they are enhanced (the returned captures are its output).
    ``enhance``: :class:`EnhanceConfig` options beside the scene's weights (the exposure step is left out)."""
    realx3d = scene == "BlueHawaii"
    root = Path("../shared/data/realx3d" if realx3d else "../shared/data/lom") / scene
    correction = "default" if realx3d else f"outputs/correction-loo/{scene}/best.pt"
    dm = LowLightDatamanagerConfig(
        dataparser=LowLightDataParserConfig(data=root),
        enhance=EnhanceConfig(correction=correction, exposure="none", **enhance),
    ).setup(device="cpu")
    lows = [to_float01(d["image"]) for d in dm.load_unenhanced_train()]  # at the training resolution
    if transform is not None:
        lows = transform(lows)
    names = [p.name for p in read_split(root, "transforms_train.json").images]
    if realx3d:
        by_stem = {p.stem: p for p in read_split(root, "transforms_reference.json").images}
        refs = [by_stem[Path(n).stem] for n in names]
    else:
        refs = [root / "high" / n for n in names]
    return lows, dm.enhancer.enhance_images(lows), refs, names


def score_variants(
    default_scenes: List[str],
    default_variants: List[str],
    variant_views: Callable[[str, List[torch.Tensor], List[torch.Tensor], str], Tuple[str, List[torch.Tensor]]],
) -> None:
    """The 2D probes' driver: ``SCENE ... -- VARIANT ...`` from the command line (defaults beside it). For each
    scene, scores the default enhancement, then each variant's ``(label, enhanced views)`` from
    ``variant_views(scene, captures, enhanced, variant)``, every one through the scene's exposure step against its
    normal-light photos (``naka-gs-enhance``'s scoring)."""
    from naka_gs_plugin.enhance.stages import ExposureStage
    from naka_gs_plugin.scripts.enhance import score_against

    args = sys.argv[1:]
    scenes, variants = (args[: args.index("--")], args[args.index("--") + 1 :]) if "--" in args else (args, [])
    for scene in scenes or default_scenes:
        lows, base, refs, names = scene_views(scene)
        print(f"{scene}, default:", flush=True)
        score_against(ExposureStage().apply_all(base), refs, names)
        for variant in variants or default_variants:
            label, out = variant_views(scene, lows, base, variant)
            print(f"{scene}, {label}:", flush=True)
            score_against(ExposureStage().apply_all(out), refs, names)
