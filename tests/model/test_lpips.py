"""LPIPS offline: the shipped weights give the published values and torchmetrics' own arithmetic."""

import importlib.util
import io
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torchmetrics.functional.image.lpips import _NoTrainLpips

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.model.lpips import CONVS, SHIPPED, LazyLPIPS, load_lpips
from tests.helpers import SHARED_REFERENCE

PAIR = SHARED_REFERENCE / "lpips"
CONVERTER = Path(__file__).resolve().parents[2] / "scripts" / "convert_lpips_weights.py"


def _image(name: str) -> torch.Tensor:
    return torch.from_numpy(read_rgb(PAIR / name)).permute(2, 0, 1)[None]


def _torchmetrics_with_shipped_weights() -> torch.nn.Module:
    """torchmetrics' LPIPS (its linear layers from its own alex.pth) with our AlexNet backbone copied in."""
    theirs = _NoTrainLpips(net="alex", pnet_rand=True)  # pnet_rand: no torchvision download
    ours = torch.load(SHIPPED, map_location="cpu", weights_only=True)
    slices = dict(zip(CONVS, ("slice1", "slice2", "slice3", "slice4", "slice5")))
    state = {f"net.{slices[i]}.{i}.{p}": ours[f"features.{i}.{p}"] for i in CONVS for p in ("weight", "bias")}
    missing = theirs.load_state_dict(state, strict=False).missing_keys
    assert not [k for k in missing if k.startswith("net.")], missing
    return theirs


def test_reference_pair_gives_the_published_values():
    metric = LazyLPIPS()
    ref, p0, p1 = _image("ex_ref.png"), _image("ex_p0.png"), _image("ex_p1.png")
    assert float(metric(ref, p0)) == pytest.approx(0.722, abs=1e-3)
    assert float(metric(ref, p1)) == pytest.approx(0.138, abs=1e-3)


def test_equals_torchmetrics_lpips_given_the_same_weights():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 3, 70, 90, generator=g)
    b = (a + 0.2 * torch.randn(3, 3, 70, 90, generator=g)).clamp(0, 1)
    ours = load_lpips()
    theirs = _torchmetrics_with_shipped_weights()
    with torch.no_grad():
        torch.testing.assert_close(ours(a, b), theirs(a, b, normalize=True).flatten(), atol=1e-5, rtol=0)
        torch.testing.assert_close(ours(a, a), torch.zeros(3), atol=1e-6, rtol=0)


def test_shipped_linear_layers_are_torchmetrics_alex_pth_bit_for_bit():
    import torchmetrics.functional.image.lpips as tm

    theirs = torch.load(Path(tm.__file__).parent / "lpips_models" / "alex.pth", map_location="cpu", weights_only=True)
    ours = torch.load(SHIPPED, map_location="cpu", weights_only=True)
    for i in range(5):
        assert torch.equal(ours[f"lins.{i}.weight"], theirs[f"lin{i}.model.1.weight"])


def test_lazy_metric_builds_on_first_call_and_follows_the_device():
    metric = LazyLPIPS()
    assert metric._metric is None
    x = torch.rand(1, 3, 32, 32)
    assert float(metric(x, x)) == pytest.approx(0.0, abs=1e-6)
    assert metric._metric is not None and next(metric._metric.parameters()).device.type == "cpu"


def test_building_and_calling_the_metric_leaves_the_random_state_alone():
    """Evaluation during training must not change the training that follows (densification draws random numbers)."""
    torch.manual_seed(3)
    before = torch.get_rng_state()
    metric = LazyLPIPS()
    x = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    metric(x, x.flip(-1))
    assert torch.equal(torch.get_rng_state(), before)


def test_weights_file_errors_are_one_line_naming_the_file(tmp_path):
    missing = tmp_path / "nope.pth"
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a torch file")
    nan = tmp_path / "nan.pth"
    state = {f"features.{i}.{p}": v for i in CONVS for p, v in (("weight", None), ("bias", None))}
    shipped = torch.load(SHIPPED, map_location="cpu", weights_only=True)
    state = {k: torch.full_like(shipped[k], float("nan")) for k in state}
    torch.save(state, nan)
    for path, says in ((missing, "not found"), (garbage, "not a readable"), (nan, "NaN")):
        with pytest.raises(ValueError) as info:
            load_lpips(path)
        assert str(path) in str(info.value) and says in str(info.value) and "\n" not in str(info.value)


def _converter():
    spec = importlib.util.spec_from_file_location("convert_lpips_weights", CONVERTER)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_converter_unpickles_numpy_arrays_and_refuses_anything_else():
    conv = _converter()
    arrays = {"AlexNet_0": {"Conv_0": {"kernel": np.ones((2, 2, 3, 4), np.float32)}}}
    back = conv.numpy_only_loads(pickle.dumps(arrays))
    assert np.array_equal(back["AlexNet_0"]["Conv_0"]["kernel"], arrays["AlexNet_0"]["Conv_0"]["kernel"])

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    with pytest.raises(pickle.UnpicklingError, match="refused global builtins.print"):
        conv.numpy_only_loads(pickle.dumps(Evil()))
    with pytest.raises(pickle.UnpicklingError):
        conv.numpy_only_loads(io.BytesIO(pickle.dumps(torch.nn.Linear(1, 1))).read())


def test_converter_turns_hwio_kernels_into_torch_layout():
    conv = _converter()
    g = np.random.default_rng(0)
    ckpt = {"AlexNet_0": {}}
    shapes = {0: (11, 11, 3, 64), 1: (5, 5, 64, 192), 2: (3, 3, 192, 384), 3: (3, 3, 384, 256), 4: (3, 3, 256, 256)}
    for i, shape in shapes.items():
        ckpt["AlexNet_0"][f"Conv_{i}"] = {"kernel": g.random(shape, np.float32), "bias": g.random(shape[3], np.float32)}
    for i, c in enumerate((64, 192, 384, 256, 256)):
        ckpt[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": g.random((1, 1, c, 1), np.float32)}}
    state = conv.convert(ckpt)
    k = ckpt["AlexNet_0"]["Conv_1"]["kernel"]
    assert state["features.3.weight"].shape == (192, 64, 5, 5)
    assert float(state["features.3.weight"][7, 5, 1, 2]) == k[1, 2, 5, 7]  # torch [O, I, H, W] = HWIO [H, W, I, O]
    assert state["lins.2.weight"].shape == (1, 384, 1, 1)
    model = load_lpips()
    model.load_state_dict(state)  # every key and shape our module expects
