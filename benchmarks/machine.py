"""What a benchmark ran on: the CPU, the kernels PyTorch and oneDNN use there, the thread count.

Every bench prints :func:`describe_cpu` first, since ratios between code paths differ between CPU
kinds (e.g. bfloat16 is fast only with native support; see ``python -m benchmarks.correction_speed``).
"""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    """``model name`` of /proc/cpuinfo with its family/model numbers (they tell a Zen 3 from a Zen 4
    where the name is only "AMD EPYC"), else ``platform.processor()``."""
    fields = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            key = key.strip()
            if key in ("model name", "cpu family", "model") and key not in fields:
                fields[key] = value.strip()
            if not line.strip() and fields:
                break
    except OSError:
        return platform.processor() or platform.machine()
    name = fields.get("model name", platform.processor() or platform.machine())
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def describe_cpu() -> str:
    """One line: CPU model, ISA features that matter here, ATen capability, native bf16, threads."""
    import torch

    from naka_gs_plugin.cpu import cpu_has, native_bf16

    features = [
        name
        for name, present in (
            ("AVX2", cpu_has("avx2")),
            ("AVX-512", cpu_has("avx512")),
            ("AVX-512 BF16", cpu_has("avx512_bf16")),
            ("AMX", cpu_has("amx_tile")),
        )
        if present
    ]
    caps = [f"{k}={os.environ[k]}" for k in ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY") if os.environ.get(k)]
    native, why = native_bf16()
    return (
        f"CPU: {cpu_model()}, {os.cpu_count()} logical CPUs; {', '.join(features) or 'no AVX2'}; "
        f"PyTorch kernels {torch.backends.cpu.get_cpu_capability()}"
        + (f" ({', '.join(caps)})" if caps else "")
        + f"; native bf16: {'yes' if native else 'no'} ({why}); torch threads {torch.get_num_threads()}"
    )
