"""``naka-gs-eval-correction --lol DIR --lom SCENE ...``: the correction network scored on held-out pairs.

The scores (all pixels, bright pixels, edges) are described in :mod:`naka_gs_plugin.bench.correction_eval`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.bench.correction_eval import gray_world, markdown, masks, means_table, scores
from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS, load_correction
from naka_gs_plugin.enhance.correction import MODES, CorrectionRunner
from naka_gs_plugin.enhance.correction_train import Pair, lol_pairs, lom_pairs, with_naka


@dataclass
class EvalCorrection:
    """Score input / Naka / Naka + gray world / Naka + network on held-out pairs."""

    lol: Tuple[Path, ...] = ()
    """LOL-style roots (their ``eval/{low,high}`` pairs are scored)."""
    lom: Tuple[Path, ...] = ()
    """lowlight-data scenes with low/ + high/ (their ``transforms_test.json`` views are scored)."""
    weights: Path = DEFAULT_WEIGHTS
    """Correction checkpoint (default: the shipped weights)."""
    modes: Tuple[str, ...] = ("exact",)
    """Network inference modes to score (``auto`` or naka_gs_plugin.enhance.correction.MODES)."""
    output: Path = Path("outputs/correction_eval.json")
    """JSON with the per-dataset means and the per-image numbers."""

    def main(self) -> Dict[str, dict]:
        unknown = [m for m in self.modes if m != "auto" and m not in MODES]
        if unknown:
            raise ValueError(f"unknown modes {unknown}; choose auto or one of {sorted(MODES)}")
        datasets: Dict[str, List[Pair]] = {}
        for root in self.lol:
            datasets[f"LOL {root.name} eval"] = lol_pairs(root, "eval")
        if self.lom:
            datasets["LOM test views"] = [p for scene in self.lom for p in lom_pairs(scene, "test")]
        if not datasets:
            raise ValueError("nothing to score: pass --lol and/or --lom")
        net = load_correction(self.weights)
        runners = {m: CorrectionRunner(net, m) for m in self.modes}
        methods = ["input", "naka", "naka+grayworld"] + [f"naka+net ({m})" for m in self.modes]
        result: Dict[str, dict] = {"weights": str(self.weights), "datasets": {}}
        for dname, pairs in datasets.items():
            per_image: Dict[str, List[dict]] = {m: [] for m in methods}
            seconds: Dict[str, List[float]] = {m: [] for m in self.modes}
            for pair in pairs:
                low_hw3 = torch.from_numpy(read_rgb(pair.low))[None]
                gt = torch.from_numpy(read_rgb(pair.high)).permute(2, 0, 1)[None]
                low = low_hw3.permute(0, 3, 1, 2).contiguous()
                naka = with_naka(low_hw3)
                preds = {"input": low, "naka": naka, "naka+grayworld": gray_world(naka)}
                for m, runner in runners.items():
                    t0 = time.perf_counter()
                    preds[f"naka+net ({m})"] = runner(low, naka)["enhanced"]
                    seconds[m].append(time.perf_counter() - t0)
                w = masks(gt)
                for m in methods:
                    per_image[m].append({"image": str(pair.low), **scores(preds[m], gt, w)})
            means = {
                m: {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "image"}
                for m, rows in per_image.items()
            }
            result["datasets"][dname] = {
                "n_images": len(pairs),
                "means": means,
                "seconds_per_image": {m: float(np.mean(s)) for m, s in seconds.items()},
                "per_image": per_image,
            }
            CONSOLE.print(means_table(f"{dname} ({len(pairs)} images)", means))
        self.output.parent.mkdir(parents=True, exist_ok=True)
        self.output.write_text(json.dumps(result, indent=1))
        CONSOLE.log(f"[naka-gs] correction evaluation written to {self.output}", markup=False)
        return result


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-eval-correction``; bad input prints one line."""
    config = tyro.cli(EvalCorrection, args=args)
    try:
        result = config.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"naka-gs-eval-correction: {err}") from None
    CONSOLE.print(markdown(result), markup=False, soft_wrap=True)


if __name__ == "__main__":
    entrypoint()
