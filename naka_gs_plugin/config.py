"""The ``naka-gs`` method: low-light datamanager + splatfacto-style model, wired for ``ns-train``.

Every ``ns-*`` command imports this module at start-up (entry point ``nerfstudio.method_configs``),
so it stays light and must not import ``nerfstudio.configs.method_configs`` (circular import:
that module discovers plugins, i.e. imports this one). The optimizer dicts are therefore spelled
out here; their values are splatfacto's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import tyro
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig
from naka_gs_plugin.pipeline import NakaGSPipelineConfig
from naka_gs_plugin.trainer import NakaGSTrainerConfig

CUDA = torch.cuda.is_available()
FUSED_ADAM_ON_CPU = not CUDA and torch.__version__ >= "2.4"
"""Whether the optimizers are torch's fused Adam (:class:`FusedAdamConfig`): on a CPU, where torch has it (2.4 on)."""
MAX_STEPS = 7000
"""7k steps on either device. On a 2-core CPU clearly better than 3k on the real-scene protocol, while 10k passes
half an hour per scene (docs/real-scenes.md). On a GPU splatfacto's schedule scored best at 7k of its 30k on the
LOM protocol and lower at every later step measured, 30k included (docs/cuda.md, "The presets on a GPU")."""

DECAY_STEPS = 30000 if CUDA else 10000
"""Steps over which the decaying learning rates reach their final values: splatfacto's 30k on a GPU, whose schedule
is kept and stopped at 7k. On the CPU 10k, still longer than the run, so the rates at step 7k are above their final
values, which scored higher on the LOM protocol than decaying fully by 7k (docs/real-scenes.md, "Slower decay")."""

FAST_STEPS, FAST_DECAY_STEPS = 3000, 4300
"""``naka-gs-fast``, a first look: the CPU default's schedule shrunk to 3k of 4.3k steps on either device
(docs/real-scenes.md, "Presets"; on a GPU its rasterizer repeats the CPU protocol's scores, docs/cuda.md)."""


EVAL_IMAGE_STEPS = 100 if CUDA else 500
"""Steps between the evaluations of one test view during training (logged to tensorboard, wandb or comet; the
viewer shows none): splatfacto's on a GPU. On a CPU a test view's full-size render and its PSNR / SSIM / LPIPS
cost several training steps and training does not depend on them (``tests/test_trainer_safety.py``), so they
run less often, and all test views are evaluated once, half way (docs/cpu.md, "Evaluating during training")."""


def cpu_schedule(decay_steps: int) -> dict:
    """Splatfacto's densification, SH and resolution schedule compressed to a ``decay_steps`` learning-rate
    schedule, as fractions of it: warm-up 3 %, screen-size splits until 33 %, densification during the
    first half (as splatfacto does), an opacity reset every 10 % (splatfacto refines every 100 steps), one
    SH degree more every 5 %, and the training images at 1/4 and 1/2 size for 30 % each. Left at
    splatfacto's 30k-step values on a 7k-10k run, screen-size splitting (radius > 5 % of the image) stays
    on for the whole run and the Gaussian count explodes (docs/design.md)."""
    return dict(
        warmup_length=round(0.03 * decay_steps),
        stop_split_at=decay_steps // 2,
        stop_screen_size_at=round(0.33 * decay_steps),
        reset_alpha_every=max(1, decay_steps // 1000),
        sh_degree_interval=round(0.05 * decay_steps),
        resolution_schedule=round(0.3 * decay_steps),
    )


CPU_SCHEDULE = {**cpu_schedule(10000), "resolution_schedule": 3250}
"""The default's schedule on a CPU (splatfacto's on CUDA): the 10k one, except that the images reach full
size at step 6,500 instead of 6,000. The last 500 steps at full size score as the last 1,000 do on the LOM
protocol (within 0.06 dB / 0.002 SSIM / 0.002 LPIPS) for 0.86x of the training time (docs/cpu.md, "Fewer
full-size steps")."""


@dataclass
class FusedAdamConfig(AdamOptimizerConfig):
    """nerfstudio's Adam with torch's ``fused`` switch, on by default on a CPU: one compiled kernel per step
    instead of a dozen whole-tensor operations per parameter (torch's CPU default), the same update to float32
    rounding. On CUDA torch's own default (foreach) is kept, as splatfacto's GPU schedule was measured with it;
    so is it on torch < 2.4, which has no fused Adam for the CPU."""

    fused: tyro.conf.Suppress[Optional[bool]] = True if FUSED_ADAM_ON_CPU else None
    """True: torch's fused Adam; None: torch's default implementation for the device. Not a command-line option
    (it changes no result); a run's config.yml records it."""


@tyro.conf.configure(tyro.conf.Suppress)
@dataclass
class InternalAdam(FusedAdamConfig):
    """Adam for a parameter group of ours that nobody should tune: kept out of ``--help`` (tyro lists every
    entry of nerfstudio's ``optimizers`` dict), still set by a run's config.yml."""


@tyro.conf.configure(tyro.conf.Suppress)
@dataclass
class InternalExponentialDecay(ExponentialDecaySchedulerConfig):
    """The schedule of such a group, kept out of ``--help`` likewise."""


def _adam(lr: float, decay_steps: int, final: float | None = None, warmup: int = 0, internal: bool = False) -> dict:
    scheduler = None
    if final is not None:
        scheduler = (InternalExponentialDecay if internal else ExponentialDecaySchedulerConfig)(
            lr_final=final, max_steps=decay_steps, warmup_steps=warmup, lr_pre_warmup=0
        )
    return {"optimizer": (InternalAdam if internal else FusedAdamConfig)(lr=lr, eps=1e-15), "scheduler": scheduler}


def _method(name: str, steps: int, decay_steps: int, schedule: dict, description: str) -> MethodSpecification:
    """A naka-gs preset: ``steps`` of a ``decay_steps`` learning-rate schedule, the model's ``schedule``."""
    warmup = min(1000, round(0.1 * decay_steps))  # splatfacto: 1000 of 30k
    return MethodSpecification(
        config=NakaGSTrainerConfig(
            # NakaGSTrainer: atomic checkpoints, Ctrl-C / SIGTERM save the current step, resume skips corrupt
            # checkpoints; the config: run folders are never overwritten, ns-eval & co. load their own folder's.
            method_name=name,
            steps_per_eval_image=EVAL_IMAGE_STEPS,
            steps_per_eval_batch=0,
            steps_per_save=2000,
            steps_per_eval_all_images=1000 if CUDA else steps // 2,
            max_num_iterations=steps,
            mixed_precision=False,
            # nerfstudio defaults to "cuda", which dies on machines without one.
            machine=MachineConfig(device_type="cuda" if CUDA else "cpu"),
            pipeline=NakaGSPipelineConfig(
                datamanager=LowLightDatamanagerConfig(),
                model=NakaGSModelConfig(**schedule),
            ),
            optimizers={
                "means": _adam(1.6e-4, decay_steps, final=1.6e-6),
                "features_dc": _adam(0.0025, decay_steps),
                "features_rest": _adam(0.0025 / 20, decay_steps),
                "opacities": _adam(0.05, decay_steps),
                "scales": _adam(0.005, decay_steps),
                "quats": _adam(0.001, decay_steps),
                "camera_opt": _adam(1e-4, decay_steps, final=5e-7, warmup=warmup),
                "bilateral_grid": _adam(2e-3, decay_steps, final=1e-4, warmup=warmup),
                "appearance": _adam(1e-3, decay_steps, final=1e-4, internal=True),
            },
            viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
            vis="viewer",
        ),
        description=description,
    )


naka_gs_method = _method(
    "naka-gs",
    MAX_STEPS,
    DECAY_STEPS,
    {} if CUDA else CPU_SCHEDULE,
    "Naka-GS: low-light 3D Gaussian Splatting (Naka-Rushton enhanced training images)",
)
naka_gs_fast_method = _method(
    "naka-gs-fast",
    FAST_STEPS,
    FAST_DECAY_STEPS,
    cpu_schedule(FAST_DECAY_STEPS),
    "Naka-GS, a first look: a shorter schedule (3k steps), about 0.4x of naka-gs's time",
)

METHODS = {spec.config.method_name: spec for spec in (naka_gs_method, naka_gs_fast_method)}
"""The registered presets by ``ns-train`` name (pyproject.toml's entry points)."""
