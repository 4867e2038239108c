"""Lean correction inference: bfloat16 fused GroupNorm/GELU kernels, the in-place forward, heap reuse."""

import math
import os

import numba
import numpy as np
import pytest
import torch
import torch.nn.functional as F

import naka_gs_plugin.cpu as cpu
import naka_gs_plugin.enhance.correction as correction
import naka_gs_plugin.enhance.lean_ops as lean_ops
from naka_gs_plugin.enhance.correction import MODES, CorrectionRunner
from naka_gs_plugin.enhance.correction_net import ChromaGuided, ChromaGuidedConfig, apply_maps
from naka_gs_plugin.enhance.lean_ops import (
    _gelu_f32,
    _group_moments,
    _patterns,
    gelu_table,
    group_norm_gelu,
    group_norm_gelu_reference,
    lean_predict_maps,
    supported,
)

MID = ChromaGuidedConfig(widths=(8, 16, 32, 64))


@numba.njit
def _gelu_rows(x):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i, 0] = _gelu_f32(x[i, 0])
    return out


def _bf16(x: torch.Tensor) -> torch.Tensor:
    return x.to(torch.bfloat16).contiguous(memory_format=torch.channels_last)


def _norm(c: int, seed: int = 0) -> torch.nn.GroupNorm:
    torch.manual_seed(seed)
    norm = torch.nn.GroupNorm(8 if c % 8 == 0 else 1, c)
    torch.nn.init.normal_(norm.weight)
    torch.nn.init.normal_(norm.bias)
    return norm.requires_grad_(False).to(torch.bfloat16)  # as in the lean network


def _bf16_values(bits: np.ndarray) -> np.ndarray:
    return torch.from_numpy(bits.view(np.int16)).view(torch.bfloat16).float().numpy()


def test_gelu_table_is_correctly_rounded_gelu_of_every_bfloat16_value():
    """The table is a fixed definition (float64 erf-GELU rounded to bfloat16), not this CPU's kernel."""
    every = torch.arange(1 << 16, dtype=torch.int32).to(torch.int16).view(torch.bfloat16)
    x = every.double().numpy()
    exact = np.array([v * math.erfc(-v / math.sqrt(2.0)) / 2 if math.isfinite(v) else math.nan for v in x])
    exact[np.isinf(x) & (x > 0)] = math.inf
    exact[np.isinf(x) & (x < 0)] = -0.0
    want = torch.from_numpy(exact).float().to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16)
    got = gelu_table()
    finite = np.isfinite(x)
    assert np.array_equal(got[finite], want[finite])
    assert np.isnan(_bf16_values(got)[np.isnan(x)]).all()


def test_gelu_table_agrees_with_pytorch_where_its_kernels_are_accurate():
    """PyTorch's bfloat16 GELU takes other vectorised paths on AVX2 and AVX-512 (inaccurate in the far
    negative tail on AVX2, overflowing near the float32 maximum on AVX-512): away from those, the table
    and this CPU's kernel agree to one bfloat16 step."""
    every = torch.arange(1 << 16, dtype=torch.int32).to(torch.int16).view(torch.bfloat16)
    pytorch = F.gelu(every).view(torch.int16).numpy().view(np.uint16)
    x, got = every.float().numpy(), gelu_table()
    normal = (np.abs(_bf16_values(got)) >= 2.0**-126) & (np.abs(_bf16_values(pytorch)) >= 2.0**-126)
    region = np.isfinite(x) & (x > -3) & (np.abs(x) < 1e30) & normal  # PyTorch flushes subnormals
    steps = np.abs(got[region].astype(np.int64) - pytorch[region].astype(np.int64))
    assert steps.max() <= 1 and (steps > 0).mean() < 0.01


def test_gelu_f32_matches_the_exact_gelu():
    x = np.concatenate([np.linspace(-14, 14, 400_001), [0.0, -0.0, 1e-30, -1e-30, 40.0, -40.0, 3e38, -3e38]])
    x = x.astype(np.float32)
    got = _gelu_rows(x[:, None].copy())[:, 0].astype(np.float64)
    ref = np.array([v * math.erfc(-v / math.sqrt(2.0)) / 2 for v in x.astype(np.float64)])
    # Within 2.5e-7 absolute near zero and two float32 steps (2^-23 relative each) elsewhere: as accurate
    # as PyTorch's own float32 kernel (measured 3.8e-7 on [-12, 12]).
    assert (np.abs(got - ref) <= 2.5e-7 + 2.0**-22 * np.abs(ref)).all()


@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("act", [False, True])
@pytest.mark.parametrize("shape", [(32, 37, 53), (64, 9, 11), (3, 41, 40)])
def test_fused_float32_group_norm_gelu_matches_pytorch(shape, act, residual):
    g = torch.Generator().manual_seed(3)
    x = (torch.randn(1, *shape, generator=g) * 3 + 1).contiguous(memory_format=torch.channels_last)
    r = torch.randn(1, *shape, generator=g).contiguous(memory_format=torch.channels_last) if residual else None
    norm = _norm(shape[0]).float()
    got = group_norm_gelu(x, norm, r, act)
    with torch.no_grad():  # the reference in float64: independent of this CPU's float32 kernels
        want = group_norm_gelu_reference(x.double(), norm.double(), None if r is None else r.double(), act)
    assert got.dtype == torch.float32 and got.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("act", [False, True])
@pytest.mark.parametrize("shape", [(32, 37, 53), (64, 9, 11), (3, 41, 40)])
def test_fused_group_norm_gelu_matches_pytorch_to_one_rounding(shape, act, residual):
    g = torch.Generator().manual_seed(3)
    x = _bf16(torch.randn(1, *shape, generator=g) * 3 + 1)
    r = _bf16(torch.randn(1, *shape, generator=g)) if residual else None
    norm = _norm(shape[0])
    got, want = group_norm_gelu(x, norm, r, act), group_norm_gelu_reference(x, norm, r, act)
    assert got.dtype == torch.bfloat16 and got.is_contiguous(memory_format=torch.channels_last)
    # The normalisation is computed as x * a + b in float32 (PyTorch: (x - mean) * rstd * gamma + beta),
    # so a normalised value may round to the neighbouring bfloat16 number (8 significant bits), which
    # the residual sum and GELU (slope <= 1.13) carry on: rarely, and never by more than that step.
    scale = F.group_norm(x.float(), norm.num_groups, norm.weight.float(), norm.bias.float(), norm.eps).abs()
    if r is not None:
        scale = scale + r.float().abs()
    diff = (got.float() - want.float()).abs()
    assert (diff <= 2.0**-7 * (1.13 * scale + want.float().abs()) + 1e-6).all()
    assert (diff > 0).float().mean() < 0.05


def test_group_moments_free_of_cancellation():
    """A channel whose mean is 100x its spread: float32 sums of squares would cancel; the shift does not."""
    rng = np.random.default_rng(0)
    vals = 256.0 + 2.0 * rng.integers(0, 3, size=(1, 8, 300, 500))  # exactly representable in bfloat16
    x = _bf16(torch.from_numpy(vals).float())
    mean, var = _group_moments(_patterns(x), 8)
    per_group = vals.reshape(8, -1)
    assert np.allclose(mean, per_group.mean(1), rtol=0, atol=1e-9)
    assert np.allclose(var, per_group.var(1), rtol=1e-9)


def test_supported_only_for_bfloat16_or_float32_channels_last_single_images():
    x = torch.randn(1, 8, 5, 6)
    assert not supported(x) and not supported(x.to(torch.bfloat16))
    assert supported(_bf16(x)) and not supported(_bf16(torch.randn(2, 8, 5, 6)))
    assert supported(x.contiguous(memory_format=torch.channels_last))
    assert not supported(x.double().contiguous(memory_format=torch.channels_last))
    with pytest.raises(ValueError, match="channels-last"):
        group_norm_gelu(x, _norm(8))
    with pytest.raises(ValueError, match="one shape and dtype"):  # mixed dtypes
        group_norm_gelu(_bf16(x), _norm(8), x.contiguous(memory_format=torch.channels_last))


def test_lean_forward_equals_predict_maps_in_float32():
    torch.manual_seed(0)
    net = ChromaGuided(MID).eval()
    low, naka = torch.rand(1, 3, 45, 61) * 0.1, torch.rand(1, 3, 45, 61)
    with torch.no_grad():
        want = net.predict_maps(low, naka)
        got = lean_predict_maps(net, low, naka)
    for a, b in zip(got, want):  # float32 summation order only (the decoders' split convolutions)
        assert (a - b).abs().max() < 1e-5


def test_lean_mode_is_bfloat16_body_with_float32_heads_and_close_to_exact():
    torch.manual_seed(0)
    net = ChromaGuided(MID).eval()
    runner = CorrectionRunner(net, "lean")
    assert runner.net.stem.conv.weight.dtype == torch.bfloat16 and runner.net.mul_head.weight.dtype == torch.float32
    assert next(net.parameters()).dtype == torch.float32  # the caller's network is untouched
    low, naka = torch.rand(1, 3, 70, 90) * 0.1, torch.rand(1, 3, 70, 90)
    with torch.no_grad():
        out, exact = runner(low, naka), net(low, naka)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mul, add = net.predict_maps(low, naka)
        autocast = {"enhanced": apply_maps(naka, mul.float(), add.float(), MID.lf_kernel, MID.lf_sigma)}
    assert out["mul_map"].dtype == torch.float32 and out["mul_map"].shape == (1, 1, 70, 90)
    # Random weights on noise amplify rounding: the bound is plain bf16 autocast's (heads included),
    # whose body rounding holds the quality bar on real images (docs/cpu.md).
    err = (out["enhanced"] - exact["enhanced"]).abs().mean()
    assert err < 2e-2 and err < 2 * (autocast["enhanced"] - exact["enhanced"]).abs().mean()
    with pytest.raises(ValueError, match="untiled"):
        CorrectionRunner(net, MODES["lean"].__class__(lean=True, tile=64))


def test_lean_f32_mode_is_float32_and_equals_exact():
    torch.manual_seed(0)
    net = ChromaGuided(MID).eval()
    runner = CorrectionRunner(net, "lean-f32")
    assert runner.net.stem.conv.weight.dtype == torch.float32
    assert runner.net.stem.conv.weight.is_contiguous(memory_format=torch.channels_last)
    low, naka = torch.rand(1, 3, 70, 90) * 0.1, torch.rand(1, 3, 70, 90)
    with torch.no_grad():
        out, exact = runner(low, naka), net(low, naka)
    for key in ("enhanced", "mul_map", "add_map"):  # float32 rounding and summation order only
        torch.testing.assert_close(out[key], exact[key], rtol=0, atol=1e-4)


@pytest.mark.parametrize("native", [True, False])
def test_auto_mode_picks_bfloat16_only_with_native_support(monkeypatch, capsys, native):
    monkeypatch.setattr(correction, "native_bf16", lambda: (native, "because"))  # the name correction uses
    monkeypatch.setattr(correction, "_RESOLVED", {})
    assert correction.resolve_mode("auto") == ("lean" if native else "lean-f32")
    assert correction.resolve_mode("auto") == ("lean" if native else "lean-f32")
    logged = capsys.readouterr().out.splitlines()
    assert logged == [f"[naka-gs] correction mode auto -> {'lean' if native else 'lean-f32'}: because"]  # once
    torch.manual_seed(0)
    runner = CorrectionRunner(ChromaGuided(MID), "auto")
    assert runner.mode == MODES["lean" if native else "lean-f32"]
    assert correction.resolve_mode("exact") == "exact"
    with pytest.raises(ValueError, match="unknown correction mode 'fast'"):
        correction.resolve_mode("fast")


def test_reuse_freed_memory_leaves_the_training_thresholds(monkeypatch):
    calls = []

    class FakeLibc:
        def mallopt(self, option, value):
            calls.append(("mallopt", option, value))
            return 1

        def malloc_trim(self, pad):
            calls.append(("trim", pad))
            return 1

    monkeypatch.setattr(lean_ops, "glibc", lambda: FakeLibc())
    monkeypatch.setattr(cpu, "glibc", lambda: FakeLibc())
    with pytest.raises(RuntimeError):
        with lean_ops.reuse_freed_memory():
            assert calls == [("mallopt", -3, 192 << 20), ("mallopt", -1, 1 << 30)]
            raise RuntimeError("the forward failed")
    # Not glibc's 128 KiB start values: pinned, they made every later training step page-fault.
    assert calls[2:] == [("mallopt", -3, 32 << 20), ("mallopt", -1, 256 << 20), ("trim", 0)]


def test_heap_reuse_only_while_the_largest_activation_is_small(monkeypatch):
    calls = []
    real = lean_ops.reuse_freed_memory
    monkeypatch.setattr(lean_ops, "reuse_freed_memory", lambda limit: calls.append(limit) or real(limit))
    torch.manual_seed(0)
    runner = CorrectionRunner(ChromaGuided(MID), "lean-f32")
    low = torch.rand(1, 3, 20, 30)
    largest = MID.widths[0] * 20 * 30 * 4  # stem width x H x W float32 bytes
    monkeypatch.setitem(lean_ops.HEAP_BLOCK_LIMIT, torch.float32, largest)
    runner(low, low)
    monkeypatch.setitem(lean_ops.HEAP_BLOCK_LIMIT, torch.float32, largest - 1)
    runner(low, low)
    assert calls == [largest]


def test_fused_kernels_keep_pytorch_thread_count():
    """numba's OpenMP pool shares the runtime with PyTorch; the kernels must not change its count, also on
    the call that starts the pool (a fresh process: the pool of this one may be running already)."""
    import subprocess
    import sys

    code = (
        "import torch\n"
        "from naka_gs_plugin.enhance.lean_ops import group_norm_gelu\n"
        "torch.set_num_threads(1)\n"
        "x = torch.randn(1, 8, 6, 5).to(memory_format=torch.channels_last)\n"
        "group_norm_gelu(x, torch.nn.GroupNorm(4, 8))\n"
        "print(torch.get_num_threads())\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    out = subprocess.run(
        [sys.executable, "-c", code], env={**env, "NUMBA_NUM_THREADS": "2"}, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == "1"
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        group_norm_gelu(_bf16(torch.randn(1, 8, 6, 5)), _norm(8))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("options", [{"method": "none"}, {"correction": "none"}])
def test_no_correction_mode_is_chosen_or_printed_without_the_network(monkeypatch, capsys, options):
    from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer

    monkeypatch.setattr(correction, "_RESOLVED", {})
    enhancer = Enhancer(EnhanceConfig(**options))
    assert enhancer.correction is None and enhancer.correction_mode == "auto"
    assert "correction mode" not in capsys.readouterr().out
