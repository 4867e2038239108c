"""The parity harness (benchmarks/cuda_parity.py): gsplat CUDA parity where CUDA is present,
the harness itself in stand-in mode (torch path as the reference, cpu-fast compared) everywhere.

Self-contained (no conftest fixtures): ``scripts/gpu/run.sh`` runs this file with ``--noconftest`` on
a GPU machine without nerfstudio or Pillow.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest
import torch

from benchmarks.cuda_parity import (
    EXACT_PAIRS_OPACITY,
    FORWARD_QUANTITIES,
    GRAD_INPUTS,
    SYNTHETIC,
    ParityConfig,
    compare,
    make_scene,
    render_all,
    run,
    run_parity,
    scene_from_checkpoint,
    torch_renderer,
    within_noise,
)

QUANTITIES = {*FORWARD_QUANTITIES, "d means2d", "absgrad", "d viewmats", *(f"d {k}" for k in GRAD_INPUTS)}
needs_cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA: gsplat's rasterization (the reference) is CUDA-only"
)


# --------------------------------------------------------------------------- CPU: the harness itself
def test_standin_cpu_fast_matches_torch_within_float32_noise(tmp_path):
    pytest.importorskip("numba")
    ref_file = tmp_path / "ref.pt"
    cfg = ParityConfig(reference="torch", scenes=("sh2-2cam-aa",), save_reference=ref_file, out_dir=tmp_path)
    result, table = run(cfg)
    assert result["reference"] == "torch" and result["unavailable"] == {}
    assert set(result["cases"]) == {"sh2-2cam-aa", f"sh2-2cam-aa/o<={EXACT_PAIRS_OPACITY}"}
    for name, case in result["cases"].items():
        assert list(case["compared"]) == ["cpu-fast"]  # torch vs itself is not a comparison
        stats = case["compared"]["cpu-fast"]
        assert set(stats) == QUANTITIES
        for quantity, s in stats.items():
            assert s["ref_max_abs"] > 0, (name, quantity)  # something was rendered and differentiated
            assert within_noise(quantity, s), (name, quantity, s)
            # Same pairs, same float32 alpha arithmetic: tighter than the harness's gsplat bounds.
            assert s["rel"] <= (1e-5 if quantity in FORWARD_QUANTITIES else 1e-4), (name, quantity, s)
        assert stats["radii"]["n_differ"] == 0
        # Two different computations (compiled float64 projection vs torch float32), not one twice.
        assert stats["image"]["n_differ"] > 0
        assert f"| {name} | cpu-fast | absgrad |" in table
    assert "| case | ours | quantity | max abs |" in table and "**no**" not in table
    assert (tmp_path / "parity.md").read_text() == table
    assert json.loads((tmp_path / "parity.json").read_text())["cases"].keys() == result["cases"].keys()

    # Against the saved reference: the same comparison without rendering the reference again.
    again = run_parity(ParityConfig(reference_file=ref_file))
    assert again["cases"] == result["cases"]


def test_harness_flags_a_convention_difference():
    # A 1 % larger scale (e.g. a missed exp or blur convention) must not pass as float32 noise.
    scene = make_scene(**SYNTHETIC["sh1"].scene_kwargs)
    ref = render_all(torch_renderer(), scene, "cpu", "classic", seed=0)
    off = render_all(torch_renderer(), {**scene, "scales": scene["scales"] * 1.01}, "cpu", "classic", seed=0)
    assert not within_noise("image", compare(ref["image"], off["image"]))
    assert not within_noise("d means", compare(ref["d means"], off["d means"]))
    assert within_noise("image", compare(ref["image"], ref["image"].clone()))


def test_checkpoint_scene_round_trip(tmp_path):
    scene = make_scene(200, 40, 30, sh_degree=3, dtype=torch.float32, scale=0.08)
    prefix = "_model.gauss_params."
    state = {
        prefix + "means": scene["means"],
        prefix + "quats": scene["quats"],
        prefix + "scales": torch.log(scene["scales"]),
        prefix + "opacities": torch.logit(scene["opacities"])[:, None],
        prefix + "features_dc": scene["colors"][:, 0],
        prefix + "features_rest": scene["colors"][:, 1:],
        "_model.other": torch.zeros(1),
    }
    path = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "pipeline": state}, path)
    loaded = scene_from_checkpoint(path, 64, 48, n_cams=3)
    assert loaded["sh_degree"] == 3 and (loaded["width"], loaded["height"]) == (64, 48)
    assert torch.allclose(loaded["colors"], scene["colors"]) and torch.equal(loaded["means"], scene["means"])
    assert torch.allclose(loaded["scales"], scene["scales"], rtol=1e-6)
    assert torch.allclose(loaded["opacities"], scene["opacities"], atol=1e-6)
    assert loaded["viewmats"].shape == (3, 4, 4) and loaded["Ks"].shape == (3, 3, 3)
    # Every camera looks at the Gaussians: their median is in front, on the optical axis.
    centre = scene["means"].median(dim=0).values
    cam = loaded["viewmats"][:, :3, :3] @ centre + loaded["viewmats"][:, :3, 3]
    assert (cam[:, 2] > 0).all() and torch.allclose(cam[:, :2], torch.zeros(3, 2), atol=1e-4)
    rot = loaded["viewmats"][:, :3, :3]
    assert torch.allclose(rot @ rot.transpose(1, 2), torch.eye(3).expand(3, 3, 3), atol=1e-5)

    subset = scene_from_checkpoint(path, 64, 48, max_gaussians=50, seed=1)
    assert subset["means"].shape == (50, 3)
    # sh_degree 0 (features_rest [N, 0, 3]): colours are sigmoid(features_dc), as in get_outputs.
    torch.save({"pipeline": {**state, prefix + "features_rest": torch.zeros(200, 0, 3)}}, path)
    flat = scene_from_checkpoint(path, 64, 48)
    assert flat["sh_degree"] is None
    assert torch.allclose(flat["colors"], torch.sigmoid(scene["colors"][:, 0]))


# -------------------------------------------------------------------------- CUDA: against gsplat 1.4.0
@needs_cuda
@pytest.mark.parametrize("torch_device", ["cpu", "cuda"])
@pytest.mark.parametrize("scene", list(SYNTHETIC))
def test_gsplat_parity(scene, torch_device):
    result = run_parity(ParityConfig(reference="gsplat", scenes=(scene,), torch_device=torch_device))
    assert result["reference"] == "gsplat"
    exact = result["cases"][f"{scene}/o<={EXACT_PAIRS_OPACITY}"]["compared"]
    assert "torch" in exact
    # Capped opacities: both composite exactly the same pairs, so only float32 rounding may differ.
    for label, stats in exact.items():
        for quantity, s in stats.items():
            assert within_noise(quantity, s), (label, quantity, s)
    # Full opacities: gsplat may add faint pairs outside the radius box (alpha <= 0.0111 * opacity
    # each), nothing else; radii are computed identically.
    for label, stats in result["cases"][scene]["compared"].items():
        assert stats["radii"]["n_differ"] == 0, label
        for quantity in ("image", "alpha"):
            assert stats[quantity]["max_abs"] <= 0.05 and stats[quantity]["mean_abs"] <= 1e-3, (label, quantity)


@pytest.mark.skipif(not os.environ.get("NAKA_GS_PARITY_CKPT"), reason="set NAKA_GS_PARITY_CKPT to a trained .ckpt")
@needs_cuda
def test_gsplat_parity_on_a_trained_checkpoint():
    path = Path(os.environ["NAKA_GS_PARITY_CKPT"])
    result = run_parity(ParityConfig(reference="gsplat", scenes=(), checkpoint=path, max_gaussians=200_000))
    ((name, case),) = result["cases"].items()
    for label, stats in case["compared"].items():
        assert stats["radii"]["n_differ"] == 0, label
        assert stats["image"]["mean_abs"] <= 1e-3, label
        for quantity, s in stats.items():
            assert math.isfinite(s["max_abs"]), (label, quantity)
