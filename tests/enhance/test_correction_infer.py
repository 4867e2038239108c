"""Correction-network inference: tiles, fast modes, checkpoints (ours and the authors'), Enhancer."""

import dataclasses
import typing

import pytest
import torch

import naka_gs_plugin.enhance.pipeline as pipeline_mod
from naka_gs_plugin.enhance.checkpoint import authors_key_map, load_correction, save_correction
from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.correction import (
    MODES,
    CorrectionRunner,
    InferenceMode,
    ModeName,
    correct_image,
    receptive_radius,
    resolve_mode,
)
from naka_gs_plugin.enhance.correction_net import ChromaGuided, ChromaGuidedConfig
from naka_gs_plugin.enhance.correction_train import half_resolution_maps
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.enhance.stages import scene_sigma

SMALL = ChromaGuidedConfig(widths=(8, 8, 8, 8), enc_residual=(0, 0, 0))
"""Narrow and shallow: fast, yet the full U-Net topology (receptive radius 108 px)."""
MID = ChromaGuidedConfig(widths=(8, 16, 32, 64))
"""What the authors' ``--base_ch 8`` builds."""


@pytest.fixture(autouse=True)
def _one_thread():
    """Small convolutions on a shared 2-core machine run far faster (and steadier) on one thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _net(config=SMALL, seed=0):
    torch.manual_seed(seed)
    return ChromaGuided(config).eval()


def _pair(h, w, seed=1):
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(1, 3, h, w, generator=g) * 0.1
    # Smooth structure plus noise, so that the maps vary over the image.
    yy, xx = torch.meshgrid(torch.linspace(0, 3, h), torch.linspace(0, 3, w), indexing="ij")
    naka = (0.5 + 0.3 * torch.sin(yy + 2 * xx))[None, None].expand(1, 3, h, w) + 0.1 * torch.rand(
        1, 3, h, w, generator=g
    )
    return low, naka.clamp(0, 1).contiguous()


def test_tiled_matches_untiled_away_from_borders():
    net = _net()
    # Not a multiple of 8, and wider than one tile's input window (64 + 2*8 + 2*112 = 304 px).
    low, naka = _pair(100, 403)
    exact = net(low, naka)
    runner = CorrectionRunner(net, InferenceMode(tile=64, blend=8))
    assert runner.mode.halo == 112 and receptive_radius(SMALL) == 108
    tiled = runner(low, naka)
    inner = (..., slice(8, -8), slice(8, -8))
    for key in ("enhanced", "mul_map", "add_map"):
        assert (tiled[key] - exact[key])[inner].abs().max() < 1e-4, key
    # Without enough context the tiles are visibly wrong: the halo is what makes them exact.
    short = CorrectionRunner(net, InferenceMode(tile=64, blend=8, halo=24))(low, naka)
    assert (short["mul_map"] - exact["mul_map"])[inner].abs().max() > 1e-3


def test_replayed_statistics_reproduce_the_forward():
    net = _net(MID)
    low, naka = _pair(37, 53)
    runner = CorrectionRunner(net, "exact")
    mul, add = runner.predict_maps_with_stats(low, naka, runner.record_stats(low, naka))
    ref_mul, ref_add = net.predict_maps(low, naka)
    assert (mul - ref_mul).abs().max() < 1e-5 and (add - ref_add).abs().max() < 1e-5


@pytest.mark.parametrize("mode", sorted(MODES))
def test_modes_finite_bounded_and_close(mode):
    net = _net()
    low, naka = _pair(96, 80)
    exact = net(low, naka)
    out = CorrectionRunner(net, mode)(low, naka)
    assert out["enhanced"].shape == naka.shape and torch.isfinite(out["enhanced"]).all()
    assert out["enhanced"].min() >= 0 and out["enhanced"].max() <= 1
    assert out["mul_map"].shape == (1, 1, 96, 80) and out["add_map"].shape == (1, 3, 96, 80)
    assert (out["mul_map"] - 1).abs().max() <= 0.6 and out["add_map"].abs().max() <= 0.25
    m = MODES[mode]
    diff = (out["enhanced"] - exact["enhanced"]).abs()
    if m.stats_scale == 1.0:
        assert diff.mean() < (2e-2 if m.bf16 else 1e-5), mode  # bf16: ~8 significant bits in the body


def test_half_resolution_validation_maps_compose_at_full_resolution():
    """With constant maps (zeroed head filters) upsampling is exact, so maps predicted at half size must
    give the exact output: the maps, not the image, are resampled, and the detail of Naka is kept."""
    net = _net()
    for head in (net.mul_head, net.add_head):
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.constant_(head.bias, 0.3)
    low, naka = _pair(61, 47)
    exact = net(low, naka)["enhanced"]
    assert (half_resolution_maps(CorrectionRunner(net, "exact"), low, naka) - exact).abs().max() < 1e-6


def test_correct_image_is_channel_last():
    net = _net()
    low, naka = _pair(20, 30)
    out = correct_image(net, low[0].permute(1, 2, 0), naka[0].permute(1, 2, 0), "exact")
    assert out.shape == (20, 30, 3)
    assert torch.allclose(out, net(low, naka)["enhanced"][0].permute(1, 2, 0))


def test_checkpoint_round_trip(tmp_path):
    net = _net(MID)
    low, naka = _pair(24, 40)
    want = net(low, naka)["enhanced"]
    full = load_correction(save_correction(net, tmp_path / "full.pt", half=False, extra={"epoch": 3}))
    assert full.config == MID and torch.equal(full(low, naka)["enhanced"], want)
    half = load_correction(save_correction(net, tmp_path / "half.pt"))
    assert all(p.dtype == torch.float32 for p in half.parameters())
    assert (half(low, naka)["enhanced"] - want).abs().max() < 1e-2


def test_loading_a_checkpoint_leaves_torchs_random_state_alone(tmp_path):
    """The network's random initialisation is overwritten by the weights: a run whose enhancement is computed
    (loading the network) must draw the same random numbers afterwards as one that finds it in the cache."""
    path = save_correction(_net(MID), tmp_path / "net.pt")
    torch.manual_seed(3)
    load_correction(path)
    after_loading = torch.rand(4)
    torch.manual_seed(3)
    assert torch.equal(torch.rand(4), after_loading)


def test_wrong_checkpoints_are_rejected_naming_the_file(tmp_path):
    path = save_correction(_net(SMALL), tmp_path / "small.pt")
    ckpt = torch.load(path, weights_only=True)
    ckpt["config"] = ChromaGuidedConfig().to_dict()  # weights of another shape
    torch.save(ckpt, tmp_path / "mismatch.pt")
    torch.save({"config": {**SMALL.to_dict(), "depth": 3}, "state_dict": ckpt["state_dict"]}, tmp_path / "badcfg.pt")
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint")
    torch.save({"weights": [1, 2]}, tmp_path / "nostate.pt")
    for name in ("mismatch.pt", "badcfg.pt", "garbage.pt", "nostate.pt"):
        with pytest.raises(ValueError, match=name) as err:
            load_correction(tmp_path / name)
        assert "\n" not in str(err.value)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_correction(tmp_path / "missing.pt")


def _authors_checkpoint(net, base_ch, mul_channels=1):
    """A checkpoint as the authors' training script writes it, with their key names."""
    inverse = {ours: theirs for theirs, ours in authors_key_map(net.config).items()}
    state = {inverse[k]: v.clone() for k, v in net.state_dict().items()}
    if mul_channels == 3:  # their older head: three filters whose mean is ours
        w, b = state["mul_head.weight"], state["mul_head.bias"]
        state["mul_head.weight"] = torch.cat([w + 0.1, w - 0.1, w])
        state["mul_head.bias"] = torch.cat([b - 0.2, b + 0.2, b])
    args = {"base_ch": base_ch, "mul_range": 0.6, "add_range": 0.25, "hf_kernel_size": 5, "hf_sigma": 1.0, "lr": 2e-4}
    return {"epoch": 7, "model": state, "optimizer": {}, "scheduler": {}, "args": args, "best_psnr": 21.5}


def test_authors_key_map_covers_their_layout():
    table = authors_key_map(ChromaGuidedConfig())
    assert sorted(table.values()) == sorted(ChromaGuided().state_dict())
    for theirs in (
        "stem.block.0.weight",
        "down1.down.block.1.bias",
        "down3.block.3.conv2.block.1.weight",  # third residual block of their down3
        "down3.block.4.fc.2.bias",  # down3's SE comes after its 3 residual blocks
        "bottleneck.3.fc.0.weight",
        "up2.reduce.block.0.weight",
        "up1.block.2.fc.2.weight",
        "fuse.1.conv1.block.1.bias",
        "add_head.bias",
    ):
        assert theirs in table, theirs


@pytest.mark.parametrize("mul_channels", [1, 3])
def test_authors_checkpoint_loads_with_same_outputs(tmp_path, mul_channels):
    net = _net(MID)
    torch.save(_authors_checkpoint(net, base_ch=8, mul_channels=mul_channels), tmp_path / "latest.pth")
    loaded = load_correction(tmp_path / "latest.pth")
    assert loaded.config == MID
    low, naka = _pair(24, 40)
    want, got = net(low, naka), loaded(low, naka)
    for key in want:
        assert (want[key] - got[key]).abs().max() < 1e-6, key
    # A bare state dict (their loader accepts one too) gets their default config: wrong size here.
    torch.save(_authors_checkpoint(net, 8)["model"], tmp_path / "bare.pth")
    with pytest.raises(ValueError, match="bare.pth"):
        load_correction(tmp_path / "bare.pth")


def _images(n=2, h=40, w=56):
    g = torch.Generator().manual_seed(3)
    return [(torch.rand(h, w, 3, generator=g) * 40).to(torch.uint8) for _ in range(n)]


def test_enhancer_applies_the_correction_and_keys_the_cache(tmp_path):
    ckpt = save_correction(_net(SMALL), tmp_path / "net.pt")
    images = _images()
    # The correction's output, then the capture's colour (tests/enhance/test_chroma.py).
    naka_only = Enhancer(EnhanceConfig(correction="none")).enhance_images(images)
    corrected_enh = Enhancer(EnhanceConfig(correction=str(ckpt), correction_mode="exact"))
    corrected = corrected_enh.enhance_images(images)
    assert corrected_enh.last_run["computed"] == 2
    low = images[0].float() / 255
    want = capture_chroma(correct_image(load_correction(ckpt), low, naka_enhance(low), "exact"), low)
    assert (corrected[0] - want).abs().max() < 1e-5  # the cache's 16-bit rounding
    assert (corrected[0] - naka_only[0]).abs().mean() > 1e-3

    def keys(**kw):
        return Enhancer(EnhanceConfig(**kw))._keys(images)

    base = keys(correction=str(ckpt), correction_mode="exact")
    assert base != keys(correction="none")
    assert base != keys(correction=str(ckpt), correction_mode="lean-f32")
    again = Enhancer(EnhanceConfig(correction=str(ckpt), correction_mode="exact"))
    again.enhance_images(images)
    assert again.last_run["computed"] == 0  # same weights and mode: cached
    save_correction(_net(SMALL, seed=5), ckpt)  # new weights in the same file
    assert keys(correction=str(ckpt), correction_mode="exact") != base


def test_sigma_auto_is_the_scene_mean_and_its_key_covers_every_view():
    images = _images(n=3)
    mean = float(torch.cat([im.double().flatten() / 255 for im in images]).mean())
    assert abs(scene_sigma(images) - mean) < 1e-7 and scene_sigma([torch.zeros(4, 4, 3)]) == 1e-3
    out = Enhancer(EnhanceConfig(sigma="auto", correction="none", use_cache=False)).enhance_images(images)
    low = images[1].float() / 255
    assert (out[1] - capture_chroma(naka_enhance(low, sigma=mean), low)).abs().max() < 1e-4  # the 16-bit rounding
    assert (out[1] - capture_chroma(naka_enhance(low, sigma=0.05), low)).abs().max() > 1e-2

    def keys(imgs, sigma):
        return Enhancer(EnhanceConfig(sigma=sigma, correction="none"))._keys(imgs)

    brighter = [images[0], images[1], images[2] + 10]
    assert keys(images, "auto")[0] != keys(brighter, "auto")[0]  # view 0's sigma depends on view 2
    assert keys(images, 0.05)[0] == keys(brighter, 0.05)[0]
    assert keys(images, "auto") != keys(images, 0.05)


@pytest.mark.parametrize("field, value", [("sigma", -1.0), ("sigma", 0.0), ("sigma", float("nan")), ("n", 0.0)])
def test_bad_naka_options_name_the_option(field, value):
    with pytest.raises(ValueError, match=rf"--pipeline\.datamanager\.enhance\.{field} must be > 0"):
        Enhancer(EnhanceConfig(correction="none", **{field: value}))


def test_missing_weights_fail_clearly(tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline_mod, "DEFAULT_WEIGHTS", tmp_path / "chroma_guided_default.pt")
    with pytest.raises(FileNotFoundError, match="chroma_guided_default.pt.*correction none"):
        Enhancer(EnhanceConfig())
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        Enhancer(EnhanceConfig(correction=str(tmp_path / "nope.pt")))
    # The raw-image baseline never uses the network.
    assert Enhancer(EnhanceConfig(method="none")).correction is None


def test_unknown_mode_rejected():
    assert set(typing.get_args(ModeName)) == set(MODES) | {"auto"}
    with pytest.raises(ValueError, match="unknown correction mode"):
        CorrectionRunner(_net(), "turbo")
    with pytest.raises(ValueError, match="multiples of 8"):
        CorrectionRunner(_net(), dataclasses.replace(MODES["tiled-lowmem"], tile=50))
    with pytest.raises(ValueError, match="lean forward"):
        CorrectionRunner(_net(), InferenceMode(bf16=True))


def test_datamanager_corrects_training_images_only(toy_scene, tmp_path):
    from naka_gs_plugin.data.images import read_stored
    from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
    from naka_gs_plugin.datamanager import LowLightDatamanagerConfig

    ckpt = save_correction(_net(SMALL), tmp_path / "net.pt")

    def dm(**enhance):
        cfg = LowLightDatamanagerConfig(
            dataparser=LowLightDataParserConfig(data=toy_scene, downscale_factor=1),
            enhance=EnhanceConfig(**enhance),
            cache_images_type="uint8",
        )
        return cfg.setup(device="cpu", test_mode="val")

    naka, corrected = dm(correction="none"), dm(correction=str(ckpt), correction_mode="exact")
    changed = [not torch.equal(a["image"], b["image"]) for a, b in zip(naka.cached_train, corrected.cached_train)]
    assert all(changed) and corrected.enhancer.last_run["computed"] == 8
    for data, path in zip(corrected.cached_eval, corrected.eval_dataset.image_filenames):
        assert torch.equal(data["image"][..., :3], torch.from_numpy(read_stored(path)))


def test_bench_times_modes_in_fresh_processes_and_writes_the_sheet(toy_scene, tmp_path):
    from PIL import Image

    from benchmarks.correction_speed import BenchCorrection

    views = tuple(sorted((toy_scene / "train").glob("*.png"))[:2])
    bench = BenchCorrection(
        image=views[0],
        weights=str(save_correction(_net(SMALL), tmp_path / "net.pt")),
        modes=("lean-f32", "lean"),
        quality_modes=(),
        threads=1,
        repeats=2,
        json_out=tmp_path / "bench.json",
        sheet=tmp_path / "sheet.png",
        sheet_views=views,
        sheet_width=32,
    )
    results = bench.main()
    assert [r["mode"] for r in results] == ["exact", "lean-f32", "lean"]
    assert results[0]["max_abs"] == 0 and results[1]["max_abs"] > 0 and results[2]["max_abs"] > 0
    assert all(r["threads"] == 1 for r in results)
    assert all(r["seconds"] > 0 and r["peak_gb"] > 0.1 for r in results)
    assert Image.open(tmp_path / "sheet.png").size == (2 * 32, 3 * 24)  # 2 views x (low, Naka, corrected)


def test_training_on_cuda_runs_the_correction_there_in_exact_mode(tmp_path):
    """``auto`` with a CUDA training device means ``exact`` on that GPU (the lean modes are CPU kernels);
    an explicit CPU mode stays on the CPU, and a CPU device resolves ``auto`` for this CPU as before."""
    ckpt = save_correction(_net(SMALL), tmp_path / "net.pt")
    on_gpu = Enhancer(EnhanceConfig(correction=str(ckpt)), device="cuda:0")
    assert (on_gpu.correction_mode, on_gpu.correction_device) == ("exact", torch.device("cuda:0"))
    assert on_gpu.correction.key()["mode"] == "exact" and on_gpu.correction.device == torch.device("cuda:0")
    lean = Enhancer(EnhanceConfig(correction=str(ckpt), correction_mode="lean-f32"), device="cuda:0")
    assert (lean.correction_mode, lean.correction_device) == ("lean-f32", torch.device("cpu"))
    on_cpu = Enhancer(EnhanceConfig(correction=str(ckpt)))
    assert (on_cpu.correction_mode, on_cpu.correction_device) == (resolve_mode("auto"), torch.device("cpu"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the correction network on the GPU")
def test_correction_on_cuda_matches_the_cpu(tmp_path):
    ckpt = save_correction(_net(SMALL), tmp_path / "net.pt")
    images = _images()
    gpu = Enhancer(EnhanceConfig(correction=str(ckpt), use_cache=False), device="cuda").enhance_images(images)
    cpu = Enhancer(EnhanceConfig(correction=str(ckpt), correction_mode="exact", use_cache=False)).enhance_images(images)
    for a, b in zip(gpu, cpu):
        assert a.device.type == "cpu"
        torch.testing.assert_close(a, b, atol=2e-4, rtol=0)  # float32 GPU vs CPU, then 16-bit rounding
