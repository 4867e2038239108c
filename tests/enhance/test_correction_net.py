"""Correction network, its loss and its training CLI (issue 6)."""

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from naka_gs_plugin.enhance.checkpoint import load_correction
from naka_gs_plugin.enhance.correction_loss import (
    CorrectionLoss,
    LossWeights,
    bright_mask,
    gray_edge_mask,
    ssim_loss,
)
from naka_gs_plugin.enhance.correction_net import (
    ChromaGuided,
    ChromaGuidedConfig,
    apply_maps,
    standardize,
)
from naka_gs_plugin.enhance.correction_train import (
    PairSet,
    TrainConfig,
    config_from_yaml,
    export_weights,
    load_sources,
    lol_pairs,
    lom_pairs,
    sim_pairs,
    train,
    training_device,
    validate,
)
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.shipped import CONFIGS

TINY = ChromaGuidedConfig(widths=(8, 8, 8, 8), enc_residual=(1, 1, 1))


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Tiny tensors: one thread is as fast and immune to oversubscription on a busy CI box."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _naka(low: torch.Tensor) -> torch.Tensor:
    return naka_enhance(low.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


@pytest.fixture(scope="module")
def net() -> ChromaGuided:
    torch.manual_seed(0)
    return ChromaGuided().eval()


def test_parameter_count_matches_reference(net):
    assert sum(p.numel() for p in net.parameters()) == 5_443_620


@pytest.mark.parametrize(
    "kind,hw",
    [
        ("black", (16, 16)),
        ("saturated", (16, 16)),
        ("constant", (9, 11)),
        ("random", (1, 1)),
        ("random", (7, 5)),
        ("random", (33, 19)),
    ],
)
def test_shapes_finite_and_map_bounds(net, kind, hw):
    g = torch.Generator().manual_seed(1)
    low = {
        "black": torch.zeros(1, 3, *hw),
        "saturated": torch.ones(1, 3, *hw),
        "constant": torch.full((1, 3, *hw), 0.3),
        "random": torch.rand(1, 3, *hw, generator=g) * 0.2,
    }[kind]
    with torch.no_grad():
        out = net(low, _naka(low))
    assert out["enhanced"].shape == (1, 3, *hw)
    assert out["mul_map"].shape == (1, 1, *hw) and out["add_map"].shape == (1, 3, *hw)
    for v in out.values():
        assert torch.isfinite(v).all()
    assert out["enhanced"].min() >= 0 and out["enhanced"].max() <= 1
    assert (out["mul_map"] > 0.4).all() and (out["mul_map"] < 1.6).all()
    assert out["add_map"].abs().max() < 0.25


def test_standardize_finite_on_constant_images():
    x = torch.full((2, 3, 5, 4), 0.7)
    z = standardize(x)  # std floored at 1e-4: float32 rounding of the mean leaves |z| ~ 1e-3, not inf/nan
    assert torch.isfinite(z).all() and z.abs().max() < 1e-2


def test_neutral_maps_reproduce_naka():
    g = torch.Generator().manual_seed(2)
    naka = torch.rand(2, 3, 13, 17, generator=g)
    out = apply_maps(naka, torch.ones(2, 1, 13, 17), torch.zeros(2, 3, 13, 17))
    assert torch.allclose(out, naka, atol=1e-6, rtol=0)
    # A network whose heads output 0 gives exactly those neutral maps.
    model = ChromaGuided(TINY)
    for head in (model.mul_head, model.add_head):
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.zeros_(head.bias)
    low = naka * 0.1
    assert torch.allclose(model(low, naka)["enhanced"], naka, atol=1e-6, rtol=0)


def test_apply_maps_rejects_wrong_map_size():
    with pytest.raises(ValueError, match="upsample"):
        apply_maps(torch.rand(1, 3, 8, 8), torch.ones(1, 1, 4, 4), torch.zeros(1, 3, 8, 8))


def test_gray_edge_mask_is_opencv_laplacian_sqrt_normalised():
    g = torch.Generator().manual_seed(3)
    gt = torch.rand(1, 3, 9, 12, generator=g)
    gray = (0.299 * gt[0, 0] + 0.587 * gt[0, 1] + 0.114 * gt[0, 2]).numpy()
    lap = np.abs(cv2.Laplacian(gray, cv2.CV_32F, ksize=3))  # default border: reflect-101
    expected = np.sqrt(lap / (lap.max() + 1e-8))
    np.testing.assert_allclose(gray_edge_mask(gt)[0, 0].numpy(), expected, atol=1e-5)
    # One bright pixel: centre 1, diagonal neighbours sqrt(2/8) = 0.5, orthogonal neighbours 0.
    dot = torch.zeros(1, 3, 5, 5)
    dot[..., 2, 2] = 1.0
    m = gray_edge_mask(dot)[0, 0]
    assert m[2, 2] == pytest.approx(1.0) and m[1, 1] == pytest.approx(0.5) and m[1, 2] == 0 and m[0, 0] == 0


def test_bright_mask_is_top_quantile_of_prediction_luma():
    ramp = torch.arange(100, dtype=torch.float32).reshape(1, 1, 10, 10) / 99.0
    pred = torch.cat([ramp.repeat(1, 3, 1, 1), (1 - ramp).repeat(1, 3, 1, 1)])
    m = bright_mask(pred)
    # 0.85 quantile of 0..99 (linear) is 84.15: values 85..99 are in, per sample.
    assert m[0].sum() == 15 and m[0, 0].flatten()[85:].all() and not m[0, 0].flatten()[:85].any()
    assert m[1].sum() == 15 and m[1, 0].flatten()[:15].all()


def test_ssim_loss_uses_zero_padding_like_the_reference():
    g = torch.Generator().manual_seed(4)
    a, b = torch.rand(2, 3, 20, 24, generator=g), torch.rand(2, 3, 20, 24, generator=g)
    x = torch.arange(11, dtype=torch.float32) - 5
    k1 = torch.exp(-(x**2) / (2 * 1.5**2))
    k1 = k1 / k1.sum()
    w = (k1[:, None] * k1[None, :]).expand(3, 1, 11, 11)

    def blur(t):
        return F.conv2d(t, w, padding=5, groups=3)

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    ref = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2) + 1e-8)
    assert ssim_loss(a, b).item() == pytest.approx(1 - ref.mean().item(), abs=1e-5)


@pytest.mark.parametrize("term", ["rgb", "chroma", "ssim", "edge", "reg", "gray", "bright"])
def test_each_loss_term_decreases_on_toy_overfit(term):
    torch.manual_seed(0)
    model = ChromaGuided(TINY)
    g = torch.Generator().manual_seed(5)
    gt = torch.rand(2, 3, 16, 16, generator=g)
    low = (gt**2.2) * torch.tensor([0.04, 0.06, 0.1])[None, :, None, None]
    naka = _naka(low)
    with pytest.warns(UserWarning, match="VGG perceptual term disabled"):
        loss_fn = CorrectionLoss()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    values = []
    for _ in range(8):
        o = model(low, naka)
        t = loss_fn(o["enhanced"], gt, naka, o["mul_map"], o["add_map"])
        values.append(t[term].item())
        opt.zero_grad()
        t[term].backward()
        opt.step()
    assert values[-1] < values[0]


def test_vgg_term_is_disabled_with_one_warning_and_bad_path_fails():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loss_fn = CorrectionLoss()
        x = torch.rand(1, 3, 8, 8)
        terms = loss_fn(x, x, x, torch.ones(1, 1, 8, 8), torch.zeros(1, 3, 8, 8))
    assert len([w for w in caught if "VGG" in str(w.message)]) == 1
    assert "feat" not in terms and terms["total"].item() == pytest.approx(terms["base"].item() + 0.0, abs=1e-6)
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        CorrectionLoss(vgg_weights=Path("nope.pth"))
    # Weight 0 for the perceptual term: no VGG needed, no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        CorrectionLoss(LossWeights(feat=0.0))


def _write_pairs(root: Path, split: str, n: int, rng: np.random.Generator, misaligned: int = 0) -> None:
    for d in ("low", "high"):
        (root / split / d).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        base = cv2.resize(rng.random((6, 8, 3)).astype(np.float32), (64, 48), interpolation=cv2.INTER_CUBIC)
        high = 0.2 + 0.7 * base.clip(0, 1)
        low = high**2.2 * np.array([0.05, 0.08, 0.12], np.float32)  # dark with a blue cast
        if i < misaligned:  # partner is another picture: must be dropped
            high = 0.2 + 0.7 * cv2.resize(rng.random((6, 8, 3)).astype(np.float32), (64, 48)).clip(0, 1)
        cv2.imwrite(str(root / split / "high" / f"{i}.png"), (high[..., ::-1] * 255).round().astype(np.uint8))
        cv2.imwrite(str(root / split / "low" / f"{i}.png"), (low[..., ::-1] * 255).round().astype(np.uint8))


def test_training_cli_improves_psnr_and_checkpoints_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    data = tmp_path / "pairs"
    _write_pairs(data, "train", 7, rng, misaligned=1)
    _write_pairs(data, "eval", 2, rng)
    cfg = TrainConfig(
        output_dir=tmp_path / "run",
        model=TINY,
        lol=(data,),
        epochs=2,
        batch_size=4,
        crop=32,
        images_per_epoch=16,
        lr=3e-3,
        log_every=0,
    )
    with pytest.warns(UserWarning, match="VGG"):
        history = train(cfg)
    psnrs = [v["psnr"] for v in history["val"]]
    assert history["epoch"] == [0, 1, 2] and psnrs[2] > psnrs[0] + 1.0
    run = tmp_path / "run"
    assert json.loads((run / "history.json").read_text())["epoch"] == [0, 1, 2]
    ckpt = torch.load(run / "latest.pt", map_location="cpu", weights_only=True)
    assert ckpt["epoch"] == 2 and ckpt["config"] == TINY.to_dict() and "optimizer" in ckpt
    assert ckpt["train_config"]["crop"] == 32
    val = PairSet(lol_pairs(data, "eval"), "v")
    # Round trip: the saved weights reproduce the logged validation PSNR.
    assert validate(load_correction(run / "latest.pt"), val)["psnr"] == pytest.approx(psnrs[2], abs=1e-4)
    best = max(range(3), key=lambda i: psnrs[i])
    assert validate(load_correction(run / "best.pt"), val)["psnr"] == pytest.approx(psnrs[best], abs=1e-4)
    # Resume continues the epochs from latest.pt.
    cfg.epochs, cfg.resume = 3, run / "latest.pt"
    with pytest.warns(UserWarning, match="VGG"):
        history = train(cfg)
    assert history["epoch"] == [0, 1, 2, 3] and history["val"][:3] == [{"psnr_lol": p, "psnr": p} for p in psnrs]
    # Export: float16 weights + config + provenance, loadable, same outputs up to float16 rounding.
    shipped = export_weights(run / "best.pt", tmp_path / "shipped.pt")
    raw = torch.load(shipped, map_location="cpu", weights_only=True)
    assert "optimizer" not in raw and all(v.dtype == torch.float16 for v in raw["state_dict"].values())
    assert raw["provenance"]["val_psnr"][0]["psnr"] == pytest.approx(psnrs[0])
    low = torch.rand(1, 3, 24, 20, generator=torch.Generator().manual_seed(6)) * 0.2
    with torch.no_grad():
        a, b = load_correction(run / "best.pt")(low, _naka(low)), load_correction(shipped)(low, _naka(low))
    assert (a["enhanced"] - b["enhanced"]).abs().max() < 1e-2


def test_misaligned_pairs_are_dropped(tmp_path):
    rng = np.random.default_rng(1)
    _write_pairs(tmp_path, "train", 4, rng, misaligned=2)
    pairs = PairSet(lol_pairs(tmp_path, "train"), "t")
    dropped = pairs.drop_misaligned(0.3)
    assert sorted(Path(n).name for n, _ in dropped) == ["0.png", "1.png"] and len(pairs) == 2


def test_lom_and_sim_pair_discovery(tmp_path, toy_scene):
    scene = tmp_path / "lom"
    for d in ("low", "high"):
        (scene / d).mkdir(parents=True)
        for n in ("1.JPG", "2.JPG"):
            cv2.imwrite(str(scene / d / n), np.zeros((4, 4, 3), np.uint8))
    (scene / "transforms_train.json").write_text(json.dumps({"frames": [{"file_path": "low/2.JPG"}]}))
    (scene / "transforms_test.json").write_text(json.dumps({"frames": [{"file_path": "high/1.JPG"}]}))
    (tr,), (te,) = lom_pairs(scene, "train"), lom_pairs(scene, "test")
    assert (tr.low, tr.high) == (scene / "low/2.JPG", scene / "high/2.JPG")
    assert (te.low, te.high) == (scene / "low/1.JPG", scene / "high/1.JPG")
    (scene / "high/2.JPG").unlink()
    with pytest.raises(FileNotFoundError, match="high/2.JPG"):
        lom_pairs(scene, "train")
    sims = sim_pairs(toy_scene)
    assert len(sims) == 8 and all(p.high.parent.name == "train_gt" and p.low.stem == p.high.stem for p in sims)


def test_hold_out_leaves_a_scene_out_of_training_and_validation(tmp_path):
    scenes = []
    for name in ("sofa", "bike"):
        scene = tmp_path / name
        for d in ("low", "high"):
            (scene / d).mkdir(parents=True)
            for n in ("1.JPG", "2.JPG"):
                cv2.imwrite(str(scene / d / n), np.full((8, 8, 3), 40, np.uint8))
        (scene / "transforms_train.json").write_text(json.dumps({"frames": [{"file_path": "low/2.JPG"}]}))
        (scene / "transforms_test.json").write_text(json.dumps({"frames": [{"file_path": "high/1.JPG"}]}))
        scenes.append(scene)
    train, val, _ = load_sources(TrainConfig(lom=tuple(scenes), hold_out=("sofa",), min_edge_correlation=-1.0))
    assert {p.low.parent.parent.name for p in train.pairs + val.pairs} == {"bike"}
    with pytest.raises(ValueError, match=r"--hold-out chair names no --lom/--sim scene"):
        load_sources(TrainConfig(lom=tuple(scenes), hold_out=("chair",)))


def test_recipe_yaml_loads_and_unknown_keys_fail(tmp_path):
    cfg = config_from_yaml(CONFIGS / "correction/default.yaml")
    assert cfg.crop > 0 and cfg.lol and len(cfg.lom) == 4 and isinstance(cfg.lom[0], Path)
    gpu = config_from_yaml(CONFIGS / "correction/gpu.yaml")
    # The GPU recipe is the CPU one with the paper's crops and a longer schedule: same data and optimizer.
    assert (gpu.crop, cfg.crop) == (256, 128) and gpu.epochs > cfg.epochs
    assert (gpu.lol, gpu.lom, gpu.lom_weight, gpu.lr, gpu.batch_size) == (
        cfg.lol,
        cfg.lom,
        cfg.lom_weight,
        cfg.lr,
        cfg.batch_size,
    )
    bad = tmp_path / "bad.yaml"
    bad.write_text("epochz: 3\n")
    with pytest.raises(ValueError, match="epochz"):
        config_from_yaml(bad)


def test_gray_world_equalises_channel_means():
    from benchmarks.correction_eval import gray_world

    img = torch.stack([torch.full((4, 5), 0.2), torch.full((4, 5), 0.4), torch.full((4, 5), 0.6)])[None]
    img[..., 0, 0] = img[..., 0, 0] * 0.5  # not constant
    out = gray_world(img)
    means = out.mean(dim=(2, 3))[0]
    assert torch.allclose(means, means.mean().expand(3), atol=1e-6)


def test_eval_cli_scores_methods_and_neutral_net_equals_naka(tmp_path):
    from benchmarks.correction_eval import EvalCorrection
    from naka_gs_plugin.enhance.checkpoint import save_correction

    _write_pairs(tmp_path / "pairs", "eval", 2, np.random.default_rng(2))
    model = ChromaGuided(TINY)
    for head in (model.mul_head, model.add_head):
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.zeros_(head.bias)
    weights = save_correction(model, tmp_path / "neutral.pt", half=False)
    out = tmp_path / "eval.json"
    result = EvalCorrection(lol=(tmp_path / "pairs",), weights=weights, modes=("exact",), output=out).main()
    means = json.loads(out.read_text())["datasets"]["LOL pairs eval"]["means"]
    assert set(means) == {"input", "naka", "naka+grayworld", "naka+net (exact)"}
    assert means["naka+net (exact)"]["psnr_all"] == pytest.approx(means["naka"]["psnr_all"], abs=1e-3)
    assert means["naka+net (exact)"]["lpips_all"] == pytest.approx(means["naka"]["lpips_all"], abs=1e-3)
    assert means["naka"]["psnr_all"] > means["input"]["psnr_all"]
    assert all(0.0 <= m["lpips_all"] < 1.5 for m in means.values())
    assert result["datasets"]["LOL pairs eval"]["n_images"] == 2


def test_neutral_init_starts_from_the_naka_image(tmp_path):
    data = tmp_path / "pairs"
    rng = np.random.default_rng(3)
    _write_pairs(data, "train", 4, rng)
    _write_pairs(data, "eval", 2, rng)
    cfg = TrainConfig(
        output_dir=tmp_path / "run",
        model=TINY,
        neutral_init=True,
        lol=(data,),
        epochs=1,
        batch_size=4,
        crop=32,
        log_every=0,
    )
    with pytest.warns(UserWarning, match="VGG"):
        history = train(cfg)
    val = PairSet(lol_pairs(data, "eval"), "v")
    naka_psnr = np.mean(
        [
            10
            * np.log10(
                1
                / (
                    (
                        (
                            _naka(torch.from_numpy(lo / 255.0).float().permute(2, 0, 1)[None])
                            - torch.from_numpy(hi / 255.0).float().permute(2, 0, 1)[None]
                        )
                        ** 2
                    )
                    .mean()
                    .item()
                    + 1e-8
                )
            )
            for lo, hi in zip(val.low, val.high)
        ]
    )
    assert history["val"][0]["psnr"] == pytest.approx(naka_psnr, abs=1e-3)


def test_training_device_choice_and_bad_names():
    """``--device auto`` is CUDA where there is one, else the CPU; unusable names fail naming the option."""
    assert training_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert training_device("cpu") == torch.device("cpu")
    for bad, why in (("gpu", "not a device"), ("meta", "runs on cpu or cuda")):
        with pytest.raises(ValueError, match=rf"--device '{bad}'.*{why}"):
            training_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"--device cuda: CUDA is not available.*--device cpu"):
            training_device("cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: training the correction network on the GPU")
def test_training_on_cuda_improves_psnr_and_saves_cpu_weights(tmp_path):
    rng = np.random.default_rng(0)
    data = tmp_path / "pairs"
    _write_pairs(data, "train", 6, rng)
    _write_pairs(data, "eval", 2, rng)
    cfg = TrainConfig(
        output_dir=tmp_path / "run", model=TINY, lol=(data,), epochs=2, batch_size=4, crop=32,
        images_per_epoch=16, lr=3e-3, log_every=0, device="cuda",
    )  # fmt: skip
    with pytest.warns(UserWarning, match="VGG"):
        history = train(cfg)
    psnrs = [v["psnr"] for v in history["val"]]
    assert psnrs[2] > psnrs[0] + 1.0
    net = load_correction(tmp_path / "run" / "latest.pt")  # saved on the CPU, validated there the same
    assert validate(net, PairSet(lol_pairs(data, "eval"), "v"))["psnr"] == pytest.approx(psnrs[2], abs=1e-3)


def test_iteration_seconds_times_training_steps_at_the_recipe_size(monkeypatch):
    from naka_gs_plugin.enhance import correction_train

    seen = []
    forward = ChromaGuided.forward

    def spy(self, low, naka):
        seen.append((tuple(low.shape), self.training))
        return forward(self, low, naka)

    monkeypatch.setattr(ChromaGuided, "forward", spy)
    torch.manual_seed(0)
    seconds = correction_train.iteration_seconds(TrainConfig(batch_size=2, crop=32), "cpu", repeats=2, warmup=1)
    assert seconds > 0 and np.isfinite(seconds)
    assert seen == [((2, 3, 32, 32), True)] * 3
