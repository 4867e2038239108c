"""The model's densification, SH and resolution schedule, by the device a run trains on.

On CUDA splatfacto's own 30k-step schedule (the ``naka-gs`` preset stops it at 7k, its best point on the LOM protocol
there). On a CPU the same schedule compressed to a 10k-step learning-rate schedule (:func:`cpu_schedule`): left at
splatfacto's values on a 7k-10k run, screen-size splitting (radius > 5 % of the image) stays on for the whole run and
the Gaussian count explodes (1.1 M at step 1,400 on LOM sofa at downscale 4; docs/design.md).
"""

from __future__ import annotations

import dataclasses
from typing import Dict

from nerfstudio.models.splatfacto import SplatfactoModelConfig

SCHEDULE_KEYS = (
    "warmup_length",
    "stop_split_at",
    "stop_screen_size_at",
    "reset_alpha_every",
    "sh_degree_interval",
    "resolution_schedule",
)
"""Splatfacto's fields that make up the schedule, in steps (``reset_alpha_every`` in refinements)."""


def cpu_schedule(decay_steps: int) -> Dict[str, int]:
    """Splatfacto's densification, SH and resolution schedule compressed to a ``decay_steps`` learning-rate
    schedule, as fractions of it: warm-up 3 %, screen-size splits until 33 %, densification during the
    first half (as splatfacto does), an opacity reset every 10 % (splatfacto refines every 100 steps), one
    SH degree more every 5 %, and the training images at 1/4 and 1/2 size for 30 % each."""
    return dict(
        warmup_length=round(0.03 * decay_steps),
        stop_split_at=decay_steps // 2,
        stop_screen_size_at=round(0.33 * decay_steps),
        reset_alpha_every=max(1, decay_steps // 1000),
        sh_degree_interval=round(0.05 * decay_steps),
        resolution_schedule=round(0.3 * decay_steps),
    )


CPU_DECAY_STEPS = 10000
"""The CPU default's learning-rate schedule: still longer than its 7k-step run, so the rates at step 7k are above
their final values, which scored higher on the LOM protocol than decaying fully by 7k
(records/2026-11-27-levers.md)."""

CPU_SCHEDULE = {**cpu_schedule(CPU_DECAY_STEPS), "resolution_schedule": 3250}
"""The default's schedule on a CPU: the 10k one, except that the images reach full size at step 6,500 instead of
6,000. The last 500 steps at full size score as the last 1,000 do on the LOM protocol (within 0.06 dB / 0.002 SSIM /
0.002 LPIPS) for 0.86x of the training time (records/2026-11-27-fewer-full-size-steps.md)."""

SPLATFACTO_SCHEDULE = {f.name: f.default for f in dataclasses.fields(SplatfactoModelConfig) if f.name in SCHEDULE_KEYS}
"""Splatfacto's own schedule (30k steps), kept on CUDA."""


def schedule_for_device(device_type: str) -> Dict[str, int]:
    """The default schedule for a run on ``device_type`` (nerfstudio's ``--machine.device-type``): splatfacto's on
    ``cuda``, :data:`CPU_SCHEDULE` on anything else (our CPU rasterizers)."""
    return dict(SPLATFACTO_SCHEDULE if device_type == "cuda" else CPU_SCHEDULE)
