"""The ``naka-gs`` presets: low-light datamanager + splatfacto-style model, wired for ``ns-train``; the package's roof.

Every ``ns-*`` command imports this module at start-up (entry point ``nerfstudio.method_configs``),
so it stays light and must not import ``nerfstudio.configs.method_configs`` (circular import:
that module discovers plugins, i.e. imports this one). The optimizer dicts are therefore spelled
out here; their values are splatfacto's.

Nothing here probes the machine: what differs between a CPU and a CUDA run is a table (the trainer config's
``by_device``), applied once the run's ``--machine.device-type`` is known, so ``--help`` is the same everywhere. At
import the hooks are activated only when the command line loads a naka-gs run
(:func:`~naka_gs_plugin.run.nerfstudio_hooks.activate_for_command`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional

import torch
import tyro
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig
from naka_gs_plugin.model.schedule import CPU_DECAY_STEPS, CPU_SCHEDULE, SCHEDULE_KEYS, cpu_schedule
from naka_gs_plugin.pipeline import NakaGSPipelineConfig
from naka_gs_plugin.run import nerfstudio_hooks
from naka_gs_plugin.run.config_check import register_presets
from naka_gs_plugin.trainer import NakaGSMachineConfig, NakaGSTrainerConfig

FUSED_ADAM = torch.__version__ >= "2.4"
"""Whether torch has a fused Adam for the CPU (2.4 on): the optimizers of a CPU run use it (:class:`FusedAdamConfig`)."""
MAX_STEPS = 7000
"""7k steps on either device. On a 2-core CPU clearly better than 3k on the real-scene protocol, while 10k passes
half an hour per scene (records/2026-11-30-lom-accuracy-vs-time.md). On a GPU splatfacto's schedule scored best at 7k
of its 30k on the LOM protocol and lower at every later step measured, 30k included
(records/2026-12-04-gpu-presets-h200.md)."""

GPU_DECAY_STEPS = 30000
"""Steps over which the decaying learning rates reach their final values on CUDA: splatfacto's 30k, whose schedule is
kept and stopped at 7k. On the CPU :data:`~naka_gs_plugin.model.schedule.CPU_DECAY_STEPS`."""

FAST_STEPS, FAST_DECAY_STEPS = 3000, 4300
"""``naka-gs-fast``, a first look: the CPU default's schedule shrunk to 3k of 4.3k steps on either device
(records/2026-11-29-presets-cpu.md; on a GPU its rasterizer repeats the CPU protocol's scores, docs/cuda.md)."""

GPU_EVAL_IMAGE_STEPS, CPU_EVAL_IMAGE_STEPS = 100, 500
"""Steps between the evaluations of one test view during training (logged to tensorboard, wandb or comet; the
viewer shows none): splatfacto's on a GPU. On a CPU a test view's full-size render and its PSNR / SSIM / LPIPS
cost several training steps and training does not depend on them (``tests/run/test_trainer_safety.py``), so they
run less often, and all test views are evaluated once, half way (records/2026-11-29-evaluating-during-training.md)."""


@dataclass
class FusedAdamConfig(AdamOptimizerConfig):
    """nerfstudio's Adam with torch's ``fused`` switch, on by default on a CPU: one compiled kernel per step
    instead of a dozen whole-tensor operations per parameter (torch's CPU default), the same update to float32
    rounding. On CUDA torch's own default (foreach) is kept, as splatfacto's GPU schedule was measured with it;
    so is it on torch < 2.4, which has no fused Adam for the CPU."""

    fused: tyro.conf.Suppress[Optional[bool]] = FUSED_ADAM
    """True: torch's fused Adam; None: torch's default implementation for the device (the presets leave it None
    until the run's device is known: a CPU run sets True where torch has it). Not a command-line option (it changes
    no result); a run's config.yml records it."""


@dataclass
class DecaySchedulerConfig(ExponentialDecaySchedulerConfig):
    """nerfstudio's exponential decay, whose length and warm-up may be left to the device the run trains on."""

    max_steps: Optional[int] = 1000000
    """Steps over which the rate decays to ``lr_final``; None: by device (the preset's description)."""
    warmup_steps: Optional[int] = 0
    """Steps of linear warm-up from ``lr_pre_warmup``; None: by device."""


@tyro.conf.configure(tyro.conf.Suppress)
@dataclass
class InternalAdam(FusedAdamConfig):
    """Adam for a parameter group of ours that nobody should tune: kept out of ``--help`` (tyro lists every
    entry of nerfstudio's ``optimizers`` dict), still set by a run's config.yml."""


@tyro.conf.configure(tyro.conf.Suppress)
@dataclass
class InternalExponentialDecay(DecaySchedulerConfig):
    """The schedule of such a group, kept out of ``--help`` likewise."""


def _warmup(decay_steps: int) -> int:
    return min(1000, round(0.1 * decay_steps))  # splatfacto: 1000 of 30k


def _adam(lr: float, decay_steps: Optional[int], final: Optional[float], warmup: bool, internal: bool) -> dict:
    scheduler = None
    if final is not None:
        scheduler = (InternalExponentialDecay if internal else DecaySchedulerConfig)(
            lr_final=final,
            max_steps=decay_steps,
            warmup_steps=_warmup(decay_steps) if warmup and decay_steps is not None else (None if warmup else 0),
            lr_pre_warmup=0,
        )
    optimizer = (InternalAdam if internal else FusedAdamConfig)(lr=lr, eps=1e-15, fused=None)  # by device
    return {"optimizer": optimizer, "scheduler": scheduler}


def _method(
    name: str, steps: int, decay_steps: Optional[int], schedule: Dict[str, Optional[int]], description: str
) -> MethodSpecification:
    """A naka-gs preset: ``steps`` of a ``decay_steps`` learning-rate schedule (None: by device), the model's
    ``schedule`` (a None value: by device). What each device gets is the trainer config's ``by_device`` table, applied
    once the run's device is known (``--machine.device-type``, ``auto`` by default)."""
    groups = {
        # group: (learning rate, final rate or None (constant), warm-up, kept out of --help)
        "means": (1.6e-4, 1.6e-6, False, False),
        "features_dc": (0.0025, None, False, False),
        "features_rest": (0.0025 / 20, None, False, False),
        "opacities": (0.05, None, False, False),
        "scales": (0.005, None, False, False),
        "quats": (0.001, None, False, False),
        "camera_opt": (1e-4, 5e-7, True, False),
        "bilateral_grid": (2e-3, 1e-4, True, False),
        "appearance": (1e-3, 1e-4, False, True),
    }
    optimizers = {
        group: _adam(lr, decay_steps, final, warmup, internal)
        for group, (lr, final, warmup, internal) in groups.items()
    }
    by_device: Dict[str, Dict[str, Any]] = {"cpu": {}, "cuda": {}}
    for device, decay, eval_image, eval_all in (
        ("cpu", CPU_DECAY_STEPS, CPU_EVAL_IMAGE_STEPS, steps // 2),
        ("cuda", GPU_DECAY_STEPS, GPU_EVAL_IMAGE_STEPS, 1000),
    ):
        table = by_device[device]
        table.update(steps_per_eval_image=eval_image, steps_per_eval_all_images=eval_all)
        for group, (_, final, warmup, _) in groups.items():
            if final is not None:
                table[f"optimizers.{group}.scheduler.max_steps"] = decay
                if warmup:
                    table[f"optimizers.{group}.scheduler.warmup_steps"] = _warmup(decay)
            if device == "cpu" and FUSED_ADAM:
                table[f"optimizers.{group}.optimizer.fused"] = True
    return MethodSpecification(
        config=NakaGSTrainerConfig(
            # NakaGSTrainer: atomic checkpoints, Ctrl-C / SIGTERM save the current step, resume skips corrupt
            # checkpoints; the config: run folders are never overwritten, ns-eval & co. load their own folder's.
            method_name=name,
            steps_per_eval_image=None,
            steps_per_eval_batch=0,
            steps_per_save=2000,
            steps_per_eval_all_images=None,
            max_num_iterations=steps,
            mixed_precision=False,
            machine=NakaGSMachineConfig(),
            pipeline=NakaGSPipelineConfig(
                datamanager=LowLightDatamanagerConfig(),
                model=NakaGSModelConfig(**schedule),
            ),
            optimizers=optimizers,
            viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
            vis="viewer",
            by_device=by_device,
        ),
        description=description,
    )


naka_gs_method = _method(
    "naka-gs",
    MAX_STEPS,
    None,
    {key: None for key in SCHEDULE_KEYS},
    "Naka-GS: low-light 3D Gaussian Splatting (Naka-Rushton enhanced training images). 7k steps; the schedule "
    f"follows --machine.device-type: cpu gets splatfacto's schedule compressed to {CPU_DECAY_STEPS} steps "
    f"(images at 1/4, 1/2, then full size from step {2 * CPU_SCHEDULE['resolution_schedule']}), cuda splatfacto's "
    f"own {GPU_DECAY_STEPS}-step schedule, stopped at 7k",
)
naka_gs_fast_method = _method(
    "naka-gs-fast",
    FAST_STEPS,
    FAST_DECAY_STEPS,
    cpu_schedule(FAST_DECAY_STEPS),
    "Naka-GS, a first look: a shorter schedule (3k of 4.3k steps, the same on every device), about 0.4x of "
    "naka-gs's time",
)

METHODS = {spec.config.method_name: spec for spec in (naka_gs_method, naka_gs_fast_method)}
"""The registered presets by ``ns-train`` name (pyproject.toml's entry points)."""
register_presets({name: spec.config for name, spec in METHODS.items()})
nerfstudio_hooks.activate_for_command()  # hooks on only for a command line that loads a naka-gs run
