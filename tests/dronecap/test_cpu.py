"""Thread count of the torch commands: the cores not already busy."""

from __future__ import annotations

import pytest

from dronecap import cpu


@pytest.mark.parametrize(
    ("cores", "busy_share", "expected"),
    [(2, 0.0, 2), (2, 0.2, 2), (2, 0.5, 1), (2, 1.0, 1), (8, 0.275, 6), (8, 0.0, 8)],
)
def test_idle_cores_subtracts_the_busy_cores(monkeypatch, cores, busy_share, expected):
    samples = iter([(0.0, 0.0), (100.0 * (1 - busy_share), 100.0)])  # (idle, total) jiffies
    monkeypatch.setattr(cpu.os, "cpu_count", lambda: cores)
    monkeypatch.setattr(cpu, "_cpu_times", lambda: next(samples))
    monkeypatch.setattr(cpu.time, "sleep", lambda s: None)
    assert cpu.idle_cores() == expected


def test_without_proc_stat_the_load_average_decides(monkeypatch, tmp_path):
    monkeypatch.setattr(cpu, "PROC_STAT", tmp_path / "missing")
    monkeypatch.setattr(cpu.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(cpu.os, "getloadavg", lambda: (1.0, 1.0, 1.0))
    assert cpu.idle_cores() == 1


def test_busy_cores_reads_this_machine():
    busy = cpu.busy_cores(0.05)
    assert 0.0 <= busy <= (cpu.os.cpu_count() or 1) + 1e-9


def test_requested_threads_win_and_are_set(monkeypatch):
    import torch

    before = torch.get_num_threads()
    monkeypatch.setattr(cpu, "busy_cores", lambda: 100.0)
    try:
        assert cpu.use_torch_threads(None) == 1 == torch.get_num_threads()
        assert cpu.use_torch_threads(3) == 3 == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    ("flags", "fast"),
    [("fpu avx2 avx512f avx512_bf16", False), ("fpu amx_bf16 amx_tile", True),
     ("fpu avx2 avx512f", False), ("", False)],
)  # fmt: skip
def test_fast_bf16_needs_the_amx_tiles(monkeypatch, tmp_path, flags, fast):
    info = tmp_path / "cpuinfo"
    info.write_text(f"processor\t: 0\nflags\t\t: {flags}\n")
    monkeypatch.setattr(cpu, "PROC_CPUINFO", info)
    assert cpu.fast_bf16() is fast


def test_without_cpuinfo_no_fast_bf16(monkeypatch, tmp_path):
    monkeypatch.setattr(cpu, "PROC_CPUINFO", tmp_path / "missing")
    assert cpu.fast_bf16() is False
