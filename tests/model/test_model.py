"""NakaGSModel in-process on CPU: backend choice, seeding, LPIPS, densification, NaN safety."""

import math

import pytest
import torch
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.splatfacto import RGB2SH, SplatfactoModel

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
from naka_gs_plugin.model.appearance import ViewAppearance
from naka_gs_plugin.model.lpips import LPIPSWeightsError
from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig, NonFiniteTrainingError, all_finite, viewmat_from_c2w
from tests.helpers import train_steps, upstream_sha256


def _model(n=400, seed_rgb=True, **overrides):
    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    rgb = (torch.rand(n, 3, generator=g) * 255).to(torch.uint8) if seed_rgb else torch.zeros(0, 3, dtype=torch.uint8)
    cfg = NakaGSModelConfig(sh_degree=1, **overrides)
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    return cfg.setup(scene_box=box, num_train_data=8, seed_points=(xyz, rgb)), xyz, rgb


@pytest.fixture
def frames(toy_scene):
    out = LowLightDataParserConfig(data=toy_scene, downscale_factor=1).setup().get_dataparser_outputs("train")
    images = [torch.from_numpy(read_rgb(p)) for p in out.image_filenames]
    return out.cameras, images


def test_seed_points_set_means_and_colours_on_cpu():
    model, xyz, rgb = _model()
    assert torch.equal(model.means.data, xyz)
    assert torch.allclose(model.features_dc.data, RGB2SH(rgb.float() / 255.0))
    assert model.means.device.type == "cpu"


def test_lpips_is_outside_the_module_tree():
    model, _, _ = _model()
    assert not any("lpips" in k for k in model.state_dict())


def test_auto_backend_is_cpu_fast_on_cpu_and_gsplat_on_cpu_is_refused(frames):
    cameras, _ = frames
    model, _, _ = _model()
    model.eval()
    with torch.no_grad():
        out = model.get_outputs(cameras[0:1])
    assert model._backend_logged == "cpu-fast"  # numba is a dependency
    assert out["rgb"].shape == (48, 64, 3) and torch.isfinite(out["rgb"]).all()
    assert out["depth"].shape == (48, 64, 1)
    forced, _, _ = _model(rasterizer="gsplat")
    with pytest.raises(ValueError, match="needs CUDA"):
        forced.get_outputs(cameras[0:1])


def test_viewmat_is_the_inverse_of_the_opencv_pose():
    g = torch.Generator().manual_seed(3)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g))
    c2w = torch.cat([q, torch.randn(3, 1, generator=g)], 1)[None]
    opencv = torch.eye(4)[None].repeat(1, 1, 1)
    opencv[:, :3, :4] = c2w
    opencv[:, :3, 1:3] *= -1  # OpenGL (y up, -z forward) -> OpenCV (y down, +z forward)
    assert torch.allclose(viewmat_from_c2w(c2w), torch.linalg.inv(opencv), atol=1e-5)


def test_metrics_include_lpips_offline_from_the_shipped_weights(frames, monkeypatch, tmp_path):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "empty-hub"))
    monkeypatch.setattr(
        "torchvision.models._api.load_state_dict_from_url",
        lambda *a, **k: (_ for _ in ()).throw(OSError("offline")),
    )
    cameras, images = frames
    model, _, _ = _model()
    model.eval()
    with torch.no_grad():
        outputs = model.get_outputs(cameras[0:1])
    metrics, images_dict = model.get_image_metrics_and_images(outputs, {"image": images[0]})
    assert all(math.isfinite(metrics[k]) for k in ("psnr", "ssim", "lpips")), metrics
    assert 0.0 < metrics["lpips"] < 1.5
    assert "img" in images_dict


def test_lpips_uses_a_local_backbone_file(frames, tmp_path):
    import torchvision

    torch.manual_seed(0)
    weights = tmp_path / "my_alexnet.pth"
    torch.save(torchvision.models.alexnet().state_dict(), weights)  # random: another backbone than the shipped one
    cameras, images = frames
    scores = {}
    for name, path in (("shipped", None), ("file", weights)):
        model, _, _ = _model(lpips_weights=path)
        model.eval()
        with torch.no_grad():
            outputs = model.get_outputs(cameras[0:1])
        scores[name] = model.get_image_metrics_and_images(outputs, {"image": images[0]})[0]["lpips"]
    assert math.isfinite(scores["file"]) and abs(scores["file"] - scores["shipped"]) > 1e-3, scores


def test_a_wrong_lpips_weights_file_stops_in_one_line(tmp_path):
    truncated = tmp_path / "cut.pth"
    truncated.write_bytes(b"PK\x03\x04" + b"\0" * 100)  # a zip header, then nothing: a cut-off download
    other = tmp_path / "other.pth"
    torch.save({"conv.weight": torch.zeros(3, 3)}, other)
    for path, says in ((truncated, "not a readable torch weights file"), (other, "not AlexNet weights")):
        with pytest.raises(LPIPSWeightsError) as info:  # one line "naka-gs: ..." under ns-train (a UserError)
            _model(lpips_weights=path)
        message = str(info.value)
        assert "\n" not in message and str(path) in message and says in message, message
        assert "--pipeline.model.lpips-weights" in message


def test_densification_changes_the_gaussian_count_on_cpu(frames):
    cameras, images = frames
    # DefaultStrategy refines when step > warmup, step % refine_every == 0 and, after an opacity
    # reset, only once num_train_data + refine_every steps have passed: first refinement at step 10.
    model, _, _ = _model(warmup_length=2, refine_every=2, densify_grad_thresh=1e-8, densify_size_thresh=0.02)
    grown = []
    grow = model.strategy._grow_gs
    model.strategy._grow_gs = lambda params, *a: grown.append((grow(params, *a), len(params["means"]))) or grown[-1][0]
    before = model.num_points
    train_steps(model, cameras, images, steps=11)
    (n_dupli, n_split), after_grow = grown[0]
    assert n_dupli + n_split > 0 and after_grow == before + n_dupli + n_split, "DefaultStrategy grew nothing on CPU"
    assert model.num_points != before
    assert model.strategy.absgrad and model.info["means2d"].absgrad is not None


def test_non_finite_parameters_stop_training(frames):
    cameras, images = frames
    model, _, _ = _model()
    train_steps(model, cameras, images, steps=1)
    with torch.no_grad():
        model.gauss_params["scales"][0, 0] = float("nan")
    with pytest.raises(NonFiniteTrainingError, match="non-finite Gaussian parameters \\(scales\\)"):
        model.step_post_backward(model.step)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_all_finite_agrees_with_isfinite_for_nan_and_both_infinities(dtype):
    gen = torch.Generator().manual_seed(3)
    tensor = torch.randn(200, 45, generator=gen, dtype=dtype) * 1e30
    assert all_finite(tensor) and all_finite(tensor[:0])
    for bad in (float("nan"), float("inf"), -float("inf")):
        for where in ((0, 0), (117, 31), (199, 44)):
            broken = tensor.clone()
            broken[where] = bad
            assert not all_finite(broken) and not torch.isfinite(broken).all()


def test_non_finite_loss_stops_before_the_optimizer_step(frames):
    cameras, images = frames
    model, _, _ = _model()
    model.train()
    model.step, model.optimizers = 0, {}
    outputs = model.get_outputs(cameras[0:1])
    bad = images[0].clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteTrainingError, match="non-finite loss"):
        model.get_loss_dict(outputs, {"image": bad})


def test_degenerate_gaussians_train_without_nan(frames):
    cameras, images = frames
    model, _, _ = _model(n=50)
    with torch.no_grad():
        model.gauss_params["scales"][:10] = -30.0  # ~zero extent
        model.gauss_params["scales"][10:20] = 7.0  # ~1e3
        model.gauss_params["quats"][20:30] = 0.0  # zero quaternion
        model.gauss_params["opacities"][30:40] = 30.0
        model.gauss_params["opacities"][40:50] = -30.0
    loss = train_steps(model, cameras, images, steps=2)
    assert torch.isfinite(loss)
    assert all(torch.isfinite(p).all() for p in model.gauss_params.values())


SPLATFACTO_GET_OUTPUTS_SHA256 = "ebe38a3708f07ea52b6eead101870cffdad9851c0f9d9cbdc528f11cfbdf263e"
"""nerfstudio 1.1.5's ``SplatfactoModel.get_outputs``, of which ``NakaGSModel.get_outputs`` is a copy."""


def test_upstream_get_outputs_is_the_pinned_one():
    digest = upstream_sha256(SplatfactoModel.get_outputs)
    assert digest == SPLATFACTO_GET_OUTPUTS_SHA256, (
        f"nerfstudio's SplatfactoModel.get_outputs changed (sha256 {digest}): port the change into "
        "NakaGSModel.get_outputs (naka_gs_plugin/model/naka_gs_model.py), then update the pin in tests/model/test_model.py"
    )


def test_view_appearance_averages_the_identity_and_clamps():
    app = ViewAppearance(4)
    assert all(torch.equal(app(torch.full((2, 3), 0.4), i), torch.full((2, 3), 0.4)) for i in range(4))
    with torch.no_grad():
        app.log_gain.copy_(torch.randn(4, 3, generator=torch.Generator().manual_seed(1)))
        app.offset.copy_(torch.randn(4, 3, generator=torch.Generator().manual_seed(2)) * 0.1)
    gains, offsets = zip(*(app.transform(i) for i in range(4)))
    torch.testing.assert_close(torch.stack(gains).log().mean(0), torch.zeros(3), atol=1e-6, rtol=0)
    torch.testing.assert_close(torch.stack(offsets).mean(0), torch.zeros(3), atol=1e-6, rtol=0)
    out = app(torch.rand(16, 3, generator=torch.Generator().manual_seed(3)) * 4 - 2, 0)
    assert out.min() >= 0 and out.max() <= 1
    with pytest.raises(IndexError, match="training view 4"):
        app.transform(4)


def test_appearance_applies_to_training_views_only(frames):
    cameras, _ = frames
    # full size and a fixed background in training too (splatfacto: downscaled early, random background)
    model, _, _ = _model(appearance="affine", num_downscales=0, background_color="black")
    assert set(model.get_param_groups()["appearance"]) == set(model.view_appearance.parameters())
    with torch.no_grad():
        model.view_appearance.log_gain[1] = math.log(2.0)  # view 1 twice as bright as the average
    camera = cameras[1:2]
    camera.metadata = {"cam_idx": 1}
    model.step, model.optimizers = 0, {}
    model.eval()
    with torch.no_grad():
        canonical = model.get_outputs(camera)["rgb"]
    model.train()  # with autograd: training's rasterization keeps the 2D means' gradients
    seen = model.get_outputs(camera)["rgb"].detach()
    gain = model.view_appearance.transform(1)[0]
    torch.testing.assert_close(seen, torch.clamp(canonical * gain, 0, 1))
    assert not torch.equal(seen, canonical)


def test_appearance_none_adds_no_parameters():
    model, _, _ = _model(appearance="none")
    assert model.view_appearance is None and "appearance" not in model.get_param_groups()
    assert not any(k.startswith("view_appearance") for k in model.state_dict())


def test_runs_saved_before_appearance_load_without_it():
    state = dict(NakaGSModelConfig().__dict__)
    del state["appearance"]
    cfg = NakaGSModelConfig.__new__(NakaGSModelConfig)
    cfg.__setstate__(state)
    assert cfg.appearance == "none"


def test_appearance_absorbs_one_views_exposure(frames):
    cameras, _ = frames
    # frozen Gaussians (no learning rate, no densification), full size, fixed background
    model, _, _ = _model(appearance="affine", num_downscales=0, background_color="black", stop_split_at=0)
    model.eval()
    with torch.no_grad():  # targets the Gaussians fit exactly, view 2 exposed 0.6x
        canonical = [model.get_outputs(cameras[i : i + 1])["rgb"] for i in range(len(cameras))]
    images = [im * (0.6 if i == 2 else 1.0) for i, im in enumerate(canonical)]
    frozen = {k: 0.0 for k in model.gauss_params}
    train_steps(model, cameras, images, steps=10 * len(images), lrs={**frozen, "appearance": 0.02})
    with torch.no_grad():
        ratios = torch.stack([model.view_appearance(c, i).mean() / c.mean() for i, c in enumerate(canonical)])
    others = torch.cat([ratios[:2], ratios[3:]])
    assert ratios[2] < 0.8 and others.min() > ratios[2] + 0.15, f"rendered / canonical brightness per view: {ratios}"


def test_the_loss_is_upstreams_value_and_gradient_from_the_fused_l1_and_ssim(frames):
    """The training loss comes from one node of compiled kernels (L1 and SSIM together) and equals splatfacto's own
    ``get_loss_dict`` with ``pytorch_msssim``'s module, in value and in the means' gradient."""
    from unittest import mock

    from nerfstudio.models.splatfacto import SplatfactoModel
    from pytorch_msssim import SSIM

    from naka_gs_plugin.model.ssim import SSIMLoss

    cameras, images = frames
    model, _, _ = _model()
    assert isinstance(model.ssim, SSIMLoss)
    model.train()
    model.step, model.optimizers = 0, {}
    results = []
    fused = model.ssim
    for ssim, get_loss_dict in (
        (fused, model.get_loss_dict),
        (SSIM(data_range=1.0, size_average=True, channel=3), None),
    ):
        model.ssim = ssim
        model.zero_grad()
        torch.manual_seed(0)  # splatfacto's training background is random
        outputs = model.get_outputs(cameras[0:1])
        if get_loss_dict is None:
            loss_dict = SplatfactoModel.get_loss_dict(model, outputs, {"image": images[0]})
        else:
            with mock.patch.object(SSIMLoss, "l1_ssim_loss", autospec=True, side_effect=SSIMLoss.l1_ssim_loss) as spy:
                loss_dict = get_loss_dict(outputs, {"image": images[0]})
            assert spy.call_count == 1
        loss_dict["main_loss"].backward()
        results.append((sorted(loss_dict), loss_dict["main_loss"].detach(), model.means.grad.clone()))
    assert results[0][0] == results[1][0]
    torch.testing.assert_close(results[0][1], results[1][1], rtol=0, atol=1e-6)
    torch.testing.assert_close(results[0][2], results[1][2], rtol=1e-3, atol=1e-3 * float(results[1][2].abs().max()))


def test_a_masked_loss_is_upstreams_own(frames):
    """With a mask (which the fused loss does not take), the loss is splatfacto's ``get_loss_dict``, bit for bit."""
    from nerfstudio.models.splatfacto import SplatfactoModel

    cameras, images = frames
    model, _, _ = _model()
    model.train()
    model.step, model.optimizers = 10**6, {}
    mask = torch.ones(*images[0].shape[:2], 1, dtype=torch.bool)
    mask[: mask.shape[0] // 2] = False
    losses = []
    for get_loss_dict in (model.get_loss_dict, lambda *a: SplatfactoModel.get_loss_dict(model, *a)):
        torch.manual_seed(0)
        losses.append(get_loss_dict(model.get_outputs(cameras[0:1]), {"image": images[0], "mask": mask})["main_loss"])
    assert torch.equal(losses[0], losses[1])


@pytest.mark.parametrize("case", ["equal", "nan", "float64"])
def test_pair_psnr_is_torchmetrics_value_on_edge_cases(case):
    from torchmetrics.functional.image import peak_signal_noise_ratio

    from naka_gs_plugin.model.naka_gs_model import PairPSNR

    gen = torch.Generator().manual_seed(0)
    target = torch.rand(20, 30, 3, generator=gen)
    preds = target.clone() if case == "equal" else (target + 0.05 * torch.randn(20, 30, 3, generator=gen))
    if case == "nan":
        preds[3, 4, 1] = float("nan")
    if case == "float64":
        preds, target = preds.double(), target.double()
    got, want = PairPSNR()(preds, target), peak_signal_noise_ratio(preds, target, data_range=1.0)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-5, equal_nan=True)


def test_training_metrics_are_computed_only_at_the_steps_the_trainer_writes(frames):
    from types import SimpleNamespace

    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    cameras, images = frames
    model, _, _ = _model()
    trainer = SimpleNamespace(config=SimpleNamespace(logging=SimpleNamespace(steps_per_log=10)))
    model.get_training_callbacks(
        TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=trainer)
    )
    model.train()
    model.optimizers = {}
    written = {}
    for step in (0, 3, 10, 19, 20):
        model.step = step
        written[step] = sorted(model.get_metrics_dict(model.get_outputs(cameras[0:1]), {"image": images[0]}))
    assert written[3] == written[19] == [] and written[0] == written[10] == written[20] and "psnr" in written[0]
    model.eval()
    model.step = 3
    with torch.no_grad():
        assert "psnr" in model.get_metrics_dict(model.get_outputs(cameras[0:1]), {"image": images[0]})


def test_the_psnr_is_torchmetrics_value_outside_autograd(frames):
    """Splatfacto's per-step training PSNR and eval PSNR: the value of torchmetrics' module, without a graph."""
    from torchmetrics.image import PeakSignalNoiseRatio

    cameras, images = frames
    model, _, _ = _model()
    model.train()
    model.step, model.optimizers = 10**6, {}  # past the resolution schedule: full-size renders
    torch.manual_seed(0)
    outputs = model.get_outputs(cameras[0:1])
    metrics = model.get_metrics_dict(outputs, {"image": images[0]})
    assert outputs["rgb"].requires_grad and not metrics["psnr"].requires_grad
    gt = images[0].float() / 255.0 if images[0].dtype == torch.uint8 else images[0]
    expected = PeakSignalNoiseRatio(data_range=1.0)(outputs["rgb"].detach(), gt)
    torch.testing.assert_close(metrics["psnr"], expected, rtol=0, atol=1e-5)
    model.eval()
    with torch.no_grad():
        image_metrics, _ = model.get_image_metrics_and_images(model.get_outputs(cameras[0:1]), {"image": images[0]})
    assert math.isfinite(image_metrics["psnr"])


def test_downscaled_target_is_upstreams_kept_per_image_and_renewed_when_it_changes():
    model, _, _ = _model()
    model.train()
    model.step = 0  # the schedule's first phase: 1/4 size
    g = torch.Generator().manual_seed(5)
    image = torch.rand(48, 64, 3, generator=g)
    first = model.get_gt_img(image)
    assert torch.equal(first, SplatfactoModel.get_gt_img(model, image)) and first.shape == (12, 16, 3)
    assert model.get_gt_img(image) is first  # the loss and the metrics of a step share one copy
    image.mul_(0.5)  # changed in place: computed again
    assert torch.equal(model.get_gt_img(image), SplatfactoModel.get_gt_img(model, image))
    eight_bit = (image * 255).to(torch.uint8)
    assert torch.equal(model.get_gt_img(eight_bit), SplatfactoModel.get_gt_img(model, eight_bit))
    del eight_bit
    assert len(model._downscaled_gt) == 1  # dropped with its image
    model.step = model.config.resolution_schedule * model.config.num_downscales  # full size
    assert model.get_gt_img(image) is image and not model._downscaled_gt


def test_a_viewer_interrupt_never_lands_inside_numbas_dispatch(frames):
    """nerfstudio's viewer cancels a render by raising IOChangeException from a trace function at the next traced
    line; raised in the Python helpers numba's dispatcher runs, it came out as SystemError and killed the viewer's
    render thread. Here it is raised at any line in numba's code: renders and a training step go through."""
    import os
    import sys

    from nerfstudio.viewer_legacy.server.viewer_utils import IOChangeException, SetTrace

    cameras, images = frames
    model, _, _ = _model()
    model.step, model.optimizers = 0, {}
    numba_lines = []

    def interrupt_in_numba(frame, event, arg):
        if event == "line" and f"{os.sep}numba{os.sep}" in frame.f_code.co_filename:
            numba_lines.append(frame.f_code.co_name)
            raise IOChangeException
        return interrupt_in_numba

    results = []
    for trace in (None, interrupt_in_numba):  # untraced first: every kernel imported and compiled
        model.eval()
        with SetTrace(trace), torch.no_grad():
            rendered = model.get_outputs(cameras[0:1])["rgb"]
        model.train()
        model.zero_grad()
        torch.manual_seed(0)  # splatfacto's training background is random
        with SetTrace(trace):
            loss = model.get_loss_dict(model.get_outputs(cameras[0:1]), {"image": images[0]})["main_loss"]
            loss.backward()
        results.append((rendered, loss.detach(), model.means.grad.clone()))
    assert sys.gettrace() is None and numba_lines == []
    for untraced, traced in zip(*results):
        torch.testing.assert_close(traced, untraced, rtol=0, atol=0)
