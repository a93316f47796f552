"""The CPU a command runs on: how many threads its torch work uses, what instructions it has."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

PROC_STAT = Path("/proc/stat")
PROC_CPUINFO = Path("/proc/cpuinfo")
AMX_BF16_FLAG = "amx_bf16"  # /proc/cpuinfo flag of the AMX tiles' bf16 products
SAMPLE_SECONDS = 0.2  # how long busy_cores watches the CPUs


def _cpu_times() -> tuple[float, float] | None:
    """(idle, total) jiffies of all CPUs since boot from /proc/stat, or None where it is
    missing (not Linux). Idle counts iowait too."""
    try:
        fields = PROC_STAT.read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return None
    ticks = [float(x) for x in fields]
    return ticks[3] + ticks[4], sum(ticks)


def busy_cores(interval: float = SAMPLE_SECONDS) -> float:
    """Cores busy now: the non-idle share of CPU time over ``interval`` seconds times the core
    count. Without /proc/stat, the 1-minute load average (which still counts a job that ended
    a minute ago: on this 2-core machine, right after a benchmark, it left a run 1 thread)."""
    cores = os.cpu_count() or 1
    before = _cpu_times()
    if before is None:
        return os.getloadavg()[0]
    time.sleep(interval)
    after = _cpu_times()
    total = after[1] - before[1]
    if total <= 0:
        return 0.0
    return cores * (1.0 - (after[0] - before[0]) / total)


def idle_cores() -> int:
    """The cores not already busy: ``os.cpu_count()`` minus :func:`busy_cores`, rounded, at
    least 1."""
    cores = os.cpu_count() or 1
    return max(1, min(cores, round(cores - busy_cores())))


def use_torch_threads(requested: int | None) -> int:
    """Set torch's CPU threads to ``requested``, or when None to :func:`idle_cores`; returns
    the count.

    OpenMP threads that share their cores with other busy processes wait for each other at
    every parallel region: on this 2-core machine at a load average of ~8, ``dronecap train``
    with torch's default 2 threads took 2-4 s per step against 20 ms with 1 thread. On an
    idle machine this is torch's own default (all cores).
    """
    import torch

    n = requested if requested else idle_cores()
    torch.set_num_threads(n)
    return n


def check_threads(requested: int | None) -> None:
    """InputError unless ``--threads`` is unset or a positive count (checked before any work)."""
    from dronecap.errors import InputError

    if requested is not None and requested < 1:
        raise InputError(f"--threads takes a positive number of threads, got {requested}")


def cpu_flags() -> str:
    """The instruction-set flags line of /proc/cpuinfo (the machine name where unreadable)."""
    try:
        text = PROC_CPUINFO.read_text()
    except OSError:
        return platform.machine()
    return next((line for line in text.splitlines() if line.startswith("flags")), "")


def fast_bf16() -> bool:
    """Whether bfloat16 products are faster than float32 ones on this CPU: it has AMX-BF16
    tiles (Intel Xeon 4th generation and later). AVX512-BF16 alone multiplies bf16 at half the
    float32 FMA rate (measured, docs/training.md), and elsewhere bf16 is emulated."""
    return AMX_BF16_FLAG in cpu_flags().split()
