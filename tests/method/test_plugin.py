"""Plugin registration as a user sees it: ns-train lists naka-gs and its options."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

BIN = Path(sys.executable).parent
FUSED_CPU = torch.__version__ >= "2.4"


def _run(*args):
    env = dict(os.environ, TORCHDYNAMO_DISABLE="1")
    return subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True, env=env, timeout=300)


def test_ns_train_help_lists_naka_gs_and_its_fast_preset():
    res = _run("ns-train", "--help")
    assert res.returncode == 0, res.stderr[-2000:]
    assert re.search(r"\bnaka-gs\b(?!-)", res.stdout) and "naka-gs-fast" in res.stdout


def _options(method: str) -> set:
    res = _run("ns-train", method, "--help")
    assert res.returncode == 0, res.stderr[-2000:]
    return set(re.findall(r"--[a-z][\w.-]*", res.stdout))


HIDDEN = (
    "init.voxel-size",
    "init.tau0",
    "init.beta",
    "init.iterations",
    "init.min-points",
    "init.tau-update",
    "init.seed",
    "enhance.n",
    "enhance.chroma-blur",
)
"""Knobs nobody should turn, kept out of --help (still set by a config.yml with ``--load-config``)."""
RETIRED = (
    "enhance.stats",
    "enhance.chroma",
    "enhance.exposure-curve",
    "enhance.exposure-metering",
    "enhance.cache-dir",
    "dataparser.cache-dir",
)


def test_naka_gs_help_shows_at_most_22_options_of_ours_and_no_internals():
    """What ``ns-train naka-gs --help`` adds to splatfacto's: the user's options, not PPM's internals nor the
    optimizer of the per-view appearance."""
    ours = _options("naka-gs") - _options("splatfacto")
    assert "--pipeline.datamanager.enhance.sigma" in ours and "--pipeline.init.points" in ours
    assert len(ours) <= 22 and all(o.startswith("--pipeline.") for o in ours), sorted(ours)
    shown = [o for o in ours for name in HIDDEN + RETIRED if o.endswith("." + name)]
    assert not shown, shown


def test_method_config_is_cpu_safe_and_light():
    code = (
        "import sys, naka_gs_plugin.config as c;"
        "m = c.naka_gs_method.config;"
        "import torch;"
        "assert m.method_name == 'naka-gs';"
        "assert m.machine.device_type == 'auto';"
        "assert 'nerfstudio.configs.method_configs' not in sys.modules;"
        "assert not any(k.startswith(('open3d', 'kornia')) for k in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]


def test_config_of_a_run_with_init_on_the_model_still_loads():
    """config.yml files written while ``init`` lived on the model config load with it on the pipeline."""
    import yaml

    from naka_gs_plugin.pipeline import NakaGSPipelineConfig
    from naka_gs_plugin.points.seeding import PointInitConfig

    old = NakaGSPipelineConfig()
    del old.init
    old.model.init = PointInitConfig(points="random")
    loaded = yaml.load(yaml.dump(old), Loader=yaml.Loader)
    assert loaded.init.points == "random"
    assert not hasattr(loaded.model, "init")
    fresh = yaml.load(yaml.dump(NakaGSPipelineConfig(init=PointInitConfig(points="random"))), Loader=yaml.Loader)
    assert fresh.init.points == "random"


def _resolved(spec, device: str, cuda: bool = False):
    """A copy of a preset's config as a run on ``--machine.device-type device`` settles it, on a machine with or
    without CUDA (stood in)."""
    import copy
    from unittest import mock

    import torch

    config = copy.deepcopy(spec.config)
    config.machine.device_type = device
    with mock.patch.object(torch.cuda, "is_available", lambda: cuda):
        config.resolve_device()
    return config


def _schedule(config) -> list:
    m = config.pipeline.model
    return [
        config.max_num_iterations, config.optimizers["means"]["scheduler"].max_steps, m.stop_split_at,
        m.resolution_schedule, config.machine.device_type, config.optimizers["means"]["optimizer"].fused,
        config.steps_per_eval_image, config.steps_per_eval_all_images,
    ]  # fmt: skip


def test_cpu_schedule_stops_a_10k_decay_at_7k():
    """On a CPU the run is 7k steps of a 10k schedule: learning rates decay over 10k, densification
    stops at half of it (records/2026-11-27-levers.md)."""
    from naka_gs_plugin import config

    m = _resolved(config.naka_gs_method, "cpu")
    decaying = {k: v["scheduler"] for k, v in m.optimizers.items() if v["scheduler"] is not None}
    assert {"means", "appearance"} <= set(decaying)
    assert {s.max_steps for s in decaying.values()} == {10000}
    assert m.max_num_iterations == 7000
    assert m.pipeline.model.stop_split_at == 10000 // 2 < m.max_num_iterations


def test_the_fast_preset_is_the_default_schedule_shrunk():
    """``naka-gs-fast`` is ``naka-gs`` with a shorter run: 3k of a 4.3k-step schedule, every densification, SH
    and resolution milestone at the same fraction of it. Everything else (data, enhancement, model options) is
    the default's."""
    from naka_gs_plugin import config
    from naka_gs_plugin.model.schedule import CPU_SCHEDULE, cpu_schedule

    fast, default = _resolved(config.naka_gs_fast_method, "cpu"), _resolved(config.naka_gs_method, "cpu")
    model = fast.pipeline.model
    decay = fast.optimizers["means"]["scheduler"].max_steps
    assert (fast.max_num_iterations, decay) == (3000, 4300)
    assert model.stop_split_at == decay // 2 and model.resolution_schedule == round(0.3 * decay)
    assert model.stop_screen_size_at < model.stop_split_at < fast.max_num_iterations
    # The default's own schedule on a CPU is the same function of its decay, except that its images reach full size
    # only for the last 500 steps (splatfacto: 2x2 downscales).
    own = {k: getattr(default.pipeline.model, k) for k in CPU_SCHEDULE}
    assert {k: v for k, v in own.items() if k != "resolution_schedule"} == {
        k: v for k, v in cpu_schedule(10000).items() if k != "resolution_schedule"
    }
    full_size_from = default.pipeline.model.num_downscales * own["resolution_schedule"]
    assert default.max_num_iterations - full_size_from == 500
    assert fast.pipeline.datamanager == default.pipeline.datamanager
    assert fast.pipeline.model.rasterizer == default.pipeline.model.rasterizer
    assert fast.method_name == "naka-gs-fast"


def test_the_schedule_follows_the_device_the_user_chose_not_the_machine():
    """With CUDA (stood in), ``naka-gs`` keeps splatfacto's 30k schedule (densification until 15k, full size from
    6k) and stops it at 7k, where it scored best on the LOM protocol on a GPU (records/2026-12-04-gpu-presets-h200.md);
    ``naka-gs-fast`` is the CPU's 3k of 4.3k. ``--machine.device-type cpu`` on that CUDA machine gets the CPU
    schedule, and ``auto`` is the machine's own device."""
    from naka_gs_plugin import config

    fused = True if config.FUSED_ADAM else None
    gpu = [7000, 30000, 15000, 3000, "cuda", None, 100, 1000]
    cpu = [7000, 10000, 5000, 3250, "cpu", fused, 500, 3500]
    assert _schedule(_resolved(config.naka_gs_method, "auto", cuda=True)) == gpu
    assert _schedule(_resolved(config.naka_gs_method, "cuda", cuda=True)) == gpu
    assert _schedule(_resolved(config.naka_gs_method, "cpu", cuda=True)) == cpu
    assert _schedule(_resolved(config.naka_gs_method, "auto", cuda=False)) == cpu
    assert _schedule(_resolved(config.naka_gs_fast_method, "cuda", cuda=True)) == [
        3000, 4300, 2150, 1290, "cuda", None, 100, 1000
    ]  # fmt: skip
    assert _schedule(_resolved(config.naka_gs_fast_method, "cpu", cuda=True)) == [
        3000, 4300, 2150, 1290, "cpu", fused, 500, 1500
    ]  # fmt: skip


def test_an_option_the_user_set_is_kept_whatever_the_device():
    """The device fills only what was left to it (None): ``--pipeline.model.stop-split-at 4000`` and a scheduler's
    ``max_steps`` stay as given on either device."""
    import copy

    from naka_gs_plugin import config

    spec = copy.deepcopy(config.naka_gs_method)
    spec.config.pipeline.model.stop_split_at = 4000
    spec.config.optimizers["means"]["scheduler"].max_steps = 1234
    for device in ("cpu", "cuda"):
        resolved = _resolved(spec, device, cuda=True)
        assert resolved.pipeline.model.stop_split_at == 4000
        assert resolved.optimizers["means"]["scheduler"].max_steps == 1234
        assert resolved.optimizers["quats"]["scheduler"] is None


def test_help_is_the_same_with_and_without_cuda():
    """Nothing probes the machine at import: ``ns-train naka-gs --help`` reads the same on a CUDA machine (stood in)
    as on this one, and says which schedule each device gets."""
    probe = (
        "import sys, torch\n"
        "if sys.argv[1] == 'cuda':\n"
        "    torch.cuda.is_available = lambda: True\n"
        "import tyro\n"
        "from naka_gs_plugin.config import naka_gs_method\n"
        "tyro.cli(type(naka_gs_method.config), default=naka_gs_method.config, args=['--help'],\n"
        "         description=naka_gs_method.description)\n"
    )
    env = dict(os.environ, COLUMNS="200")
    helps = [
        subprocess.run([sys.executable, "-c", probe, device], capture_output=True, text=True, timeout=300, env=env)
        for device in ("cpu", "cuda")
    ]
    assert helps[0].stdout and helps[0].stdout == helps[1].stdout, (helps[0].stderr[-2000:], helps[1].stderr[-2000:])
    text = " ".join(helps[0].stdout.split())
    assert "cpu gets splatfacto's schedule compressed" in text and "cuda splatfacto's own 30000-step" in text
    assert "(default: auto)" in text


def test_the_optimizers_are_torchs_fused_adam_on_a_cpu():
    """Every parameter group's Adam is torch's fused one on a CPU where torch has it (2.4 on), else torch's default;
    on CUDA torch's default."""
    import torch

    from naka_gs_plugin import config

    for method in config.METHODS.values():
        for device, expected in (("cpu", True if config.FUSED_ADAM else None), ("cuda", None)):
            for name, spec in _resolved(method, device, cuda=True).optimizers.items():
                built = spec["optimizer"].setup([torch.nn.Parameter(torch.zeros(4, 3))])
                assert built.defaults["fused"] is expected, (name, device)


@pytest.mark.skipif(not FUSED_CPU, reason="torch < 2.4 has no fused Adam for the CPU")
def test_the_fused_adam_step_matches_the_unfused_one():
    """The fused Adam's step matches the unfused Adam's to float32 rounding."""
    import torch

    from naka_gs_plugin import config

    g = torch.Generator().manual_seed(0)
    start, grads = torch.randn(64, 3, generator=g), torch.randn(20, 64, 3, generator=g)
    ends = []
    for fused in (True, None):
        param = torch.nn.Parameter(start.clone())
        adam = config.FusedAdamConfig(lr=1e-3, eps=1e-15, fused=fused).setup([param])
        for grad in grads:
            param.grad = grad.clone()
            adam.step()
        ends.append(param.detach())
    assert not torch.equal(ends[0], start)
    torch.testing.assert_close(ends[0], ends[1], rtol=0, atol=1e-6)
