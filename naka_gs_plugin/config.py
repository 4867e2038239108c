"""The ``naka-gs`` method: low-light datamanager + splatfacto-style model, wired for ``ns-train``.

Every ``ns-*`` command imports this module at start-up (entry point ``nerfstudio.method_configs``),
so it stays light and must not import ``nerfstudio.configs.method_configs`` (circular import:
that module discovers plugins, i.e. imports this one). The optimizer dicts are therefore spelled
out here; their values are splatfacto's.
"""

from __future__ import annotations

from dataclasses import dataclass

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
MAX_STEPS = 30000 if CUDA else 7000
"""Splatfacto's 30k steps on a GPU; on a 2-core CPU 7k: clearly better than 3k on the real-scene
protocol, while 10k passes half an hour per scene (docs/real-scenes.md)."""

DECAY_STEPS = 30000 if CUDA else 10000
"""Steps over which the decaying learning rates reach their final values. On the CPU longer than the
run, so the rates at step 7k are still above their final values, which scored higher on the LOM
protocol than decaying fully by 7k (docs/real-scenes.md, "Slower decay")."""

CPU_SCHEDULE = dict(
    warmup_length=300,
    stop_split_at=5000,
    stop_screen_size_at=3300,
    reset_alpha_every=10,
    sh_degree_interval=500,
)
"""Splatfacto's densification/SH schedule compressed to the CPU's 10k-step learning-rate schedule
(DECAY_STEPS): densify during its first half, as splatfacto does. Left at splatfacto's 30k-step values,
screen-size splitting (radius > 5% of the image) stays on for the whole run and the Gaussian count
explodes (docs/design.md)."""


@tyro.conf.configure(tyro.conf.Suppress)
@dataclass
class InternalAdam(AdamOptimizerConfig):
    """Adam for a parameter group of ours that nobody should tune: kept out of ``--help`` (tyro lists every
    entry of nerfstudio's ``optimizers`` dict), still set by a run's config.yml."""


@tyro.conf.configure(tyro.conf.Suppress)
@dataclass
class InternalExponentialDecay(ExponentialDecaySchedulerConfig):
    """The schedule of such a group, kept out of ``--help`` likewise."""


def _adam(lr: float, final: float | None = None, warmup: int = 0, internal: bool = False) -> dict:
    scheduler = None
    if final is not None:
        scheduler = (InternalExponentialDecay if internal else ExponentialDecaySchedulerConfig)(
            lr_final=final, max_steps=DECAY_STEPS, warmup_steps=warmup, lr_pre_warmup=0
        )
    return {"optimizer": (InternalAdam if internal else AdamOptimizerConfig)(lr=lr, eps=1e-15), "scheduler": scheduler}


naka_gs_method = MethodSpecification(
    config=NakaGSTrainerConfig(
        # NakaGSTrainer: atomic checkpoints, Ctrl-C / SIGTERM save the current step, resume skips corrupt
        # checkpoints; the config: run folders are never overwritten, ns-eval & co. load their own folder's.
        method_name="naka-gs",
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=MAX_STEPS,
        mixed_precision=False,
        # nerfstudio defaults to "cuda", which dies on machines without one.
        machine=MachineConfig(device_type="cuda" if CUDA else "cpu"),
        pipeline=NakaGSPipelineConfig(
            datamanager=LowLightDatamanagerConfig(),
            model=NakaGSModelConfig(**({} if CUDA else CPU_SCHEDULE)),
        ),
        optimizers={
            "means": _adam(1.6e-4, final=1.6e-6),
            "features_dc": _adam(0.0025),
            "features_rest": _adam(0.0025 / 20),
            "opacities": _adam(0.05),
            "scales": _adam(0.005),
            "quats": _adam(0.001),
            "camera_opt": _adam(1e-4, final=5e-7, warmup=1000),
            "bilateral_grid": _adam(2e-3, final=1e-4, warmup=1000),
            "appearance": _adam(1e-3, final=1e-4, internal=True),
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    ),
    description="Naka-GS: low-light 3D Gaussian Splatting (Naka-Rushton enhanced training images)",
)
