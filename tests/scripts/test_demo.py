"""The README's main job end to end on a tiny simulated scene: enhance, train both models, evaluate."""

import json
import math

from naka_gs_plugin.scripts.demo import DEFAULT_SPEC, Demo

TINY_SPEC = """
name: tiny-dark-noisy
seed: 0
scene_seed: 0
source:
  procedural: {n_train: 4, n_test: 2, width: 48, height: 36, layout: orbit, spacing: 0.2}
effects:
  - exposure: {factor: 0.012}
  - noise: {shot_gain: 0.00005, read_std: 0.0004}
  - response: {curve: srgb}
  - quantize: {}
"""


def test_default_spec_is_shipped():
    assert DEFAULT_SPEC.is_file()


def test_demo_trains_naka_gs_and_baseline_and_reports_metrics(tmp_path):
    spec = tmp_path / "tiny.yaml"
    spec.write_text(TINY_SPEC)
    report = Demo(out=tmp_path / "demo", spec=spec, steps=10, sheet_views=2).main()
    assert report["psnr_enhanced_vs_truth_db"] > report["psnr_input_vs_truth_db"] + 3.0  # Naka brightens
    for name in ("naka-gs", "baseline"):
        assert math.isfinite(report[name]["test_psnr_db"]) and 0.0 <= report[name]["test_ssim"] <= 1.0
        assert 0.0 < report[name]["test_lpips"] < 1.5  # offline, from the shipped weights
        assert report[name]["train_steps"] == 10
    saved = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert saved["naka-gs"]["test_psnr_db"] == report["naka-gs"]["test_psnr_db"]
    assert (tmp_path / "demo" / "side_by_side.png").is_file() and (tmp_path / "demo" / "test_renders.png").is_file()
