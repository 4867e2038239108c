"""naka_gs_plugin.cpu: native bfloat16 detection, the thread cap and a core lent to a child."""

import subprocess
import sys

import torch

import naka_gs_plugin.cpu as cpu


def test_native_bf16_needs_the_cpu_and_uncapped_kernels(monkeypatch):
    # raising=False: torch < 2.3 has no such probes (cpu_has reads /proc/cpuinfo there).
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    assert cpu.native_bf16() == (False, "this CPU has neither AVX-512 BF16 nor AMX")
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: True, raising=False)
    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: False)
    assert "ONEDNN_MAX_CPU_ISA" in cpu.native_bf16()[1]
    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: True)
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")
    assert cpu.native_bf16() == (False, "PyTorch's kernels run at AVX2 (ATEN_CPU_CAPABILITY caps them)")
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")
    assert cpu.native_bf16()[0]


def test_cpu_has_reads_the_kernels_flags_without_pytorchs_probe(monkeypatch, tmp_path):
    """torch < 2.3 has no ``torch.cpu._is_<feature>_supported``: the flags of /proc/cpuinfo answer instead."""
    for feature in ("avx2", "avx512", "avx512_bf16", "amx_tile"):
        monkeypatch.delattr(torch.cpu, f"_is_{feature}_supported", raising=False)
    monkeypatch.setattr(cpu, "CPUINFO", tmp_path / "cpuinfo")
    (tmp_path / "cpuinfo").write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16\n")
    assert [cpu.cpu_has(f) for f in ("avx2", "avx512", "avx512_bf16", "amx_tile")] == [True, True, True, False]
    monkeypatch.setattr(cpu, "CPUINFO", tmp_path / "absent")
    assert not cpu.cpu_has("avx2")


def test_cgroup_quota_v2_and_v1(tmp_path):
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert cpu.cgroup_cpu_limit(tmp_path) == 1.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cpu.cgroup_cpu_limit(tmp_path) is None
    (tmp_path / "cpu.max").unlink()
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("200000")
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000")
    assert cpu.cgroup_cpu_limit(tmp_path) == 2.0
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1")
    assert cpu.cgroup_cpu_limit(tmp_path) is None


def test_fit_threads_caps_at_the_usable_cpus_and_logs_once(monkeypatch, capsys):
    threads = torch.get_num_threads()
    monkeypatch.setattr(cpu, "_FITTED", {})
    monkeypatch.setattr(cpu, "cgroup_cpu_limit", lambda: 1.2)  # a container limited to 1.2 CPUs
    monkeypatch.setattr(cpu.os, "cpu_count", lambda: 64)
    monkeypatch.setattr(cpu.os, "sched_getaffinity", lambda pid: set(range(64)))
    assert cpu.usable_cpus() == (2, "the cgroup CPU quota")
    try:
        torch.set_num_threads(8)
        assert cpu.fit_threads() == 2 and torch.get_num_threads() == 2
        torch.set_num_threads(8)
        cpu.fit_threads()
        assert (
            capsys.readouterr().out == "[naka-gs] using 2 threads instead of 8: 2 CPUs usable (the cgroup CPU quota)\n"
        )
        torch.set_num_threads(1)  # fewer than usable: kept
        assert cpu.fit_threads() == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)


def test_a_lent_core_comes_back_once_the_child_has_exited(monkeypatch, tmp_path):
    """Two usable CPUs: one thread while the child runs, whatever reclaim_core is asked; two at the first
    reclaim_core after it exits, and at the block's end while it still runs."""
    monkeypatch.setattr(cpu, "usable_cpus", lambda: (2, "test"))
    go = tmp_path / "go"
    wait_for_go = f"import pathlib, time\nwhile not pathlib.Path({str(go)!r}).exists(): time.sleep(0.01)"
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        child = subprocess.Popen([sys.executable, "-c", wait_for_go])
        with cpu.core_lent(child):
            assert torch.get_num_threads() == 1
            cpu.reclaim_core()
            assert torch.get_num_threads() == 1  # still running
            go.touch()
            child.wait()
            cpu.reclaim_core()
            assert torch.get_num_threads() == 2
        assert torch.get_num_threads() == 2
        child = subprocess.Popen([sys.executable, "-c", wait_for_go])  # go exists: it exits at once
        child.wait()
        with cpu.core_lent(child):
            assert torch.get_num_threads() == 2  # nothing to lend to a child that has exited
        running = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        try:
            with cpu.core_lent(running):
                assert torch.get_num_threads() == 1
            assert torch.get_num_threads() == 2  # the block's end restores it, the child still running
        finally:
            running.kill()
            running.wait()
    finally:
        torch.set_num_threads(threads)


class _FakeLibc:
    def __init__(self):
        self.calls = []

    def mallopt(self, param, value):
        self.calls.append((param, value))
        return 1

    def malloc_trim(self, pad):
        return 1


def test_keep_freed_memory_sets_both_glibc_thresholds(monkeypatch):
    libc = _FakeLibc()
    monkeypatch.setattr(cpu.ctypes, "CDLL", lambda name: libc)
    assert cpu.keep_freed_memory()
    assert libc.calls == [(-3, 32 << 20), (-1, 256 << 20)]  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD


def test_keep_freed_memory_is_a_no_op_without_mallopt(monkeypatch):
    monkeypatch.setattr(cpu.ctypes, "CDLL", lambda name: object())  # a C library without mallopt (macOS)
    assert not cpu.keep_freed_memory()


def test_keep_freed_memory_reports_a_refused_value(monkeypatch):
    libc = _FakeLibc()
    libc.mallopt = lambda param, value: 0  # glibc refuses a value out of range
    monkeypatch.setattr(cpu.ctypes, "CDLL", lambda name: libc)
    assert not cpu.keep_freed_memory()


def test_untraced_suspends_this_threads_trace_and_restores_it():
    import sys

    lines = []

    def trace(frame, event, arg):
        if event == "line":
            lines.append(frame.f_code.co_name)
        return trace

    def probe():
        return 1

    sys.settrace(trace)
    try:
        with cpu.untraced():
            inside = sys.gettrace()
            probe()
        after = sys.gettrace()
        probe()
    finally:
        sys.settrace(None)
    assert inside is None and after is trace
    assert lines.count("probe") == 1  # traced after the block only
    with cpu.untraced():
        assert sys.gettrace() is None
    assert sys.gettrace() is None
