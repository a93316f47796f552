"""How many CPU threads a command's torch work uses."""

from __future__ import annotations

import argparse
import os


def idle_cores() -> int:
    """The cores not already busy: ``os.cpu_count()`` minus the 1-minute load average,
    rounded, at least 1."""
    cores = os.cpu_count() or 1
    return max(1, min(cores, round(cores - os.getloadavg()[0])))


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


def add_threads_argument(p: argparse.ArgumentParser) -> None:
    """The ``--threads N`` option of the commands that run torch (train, render, eval)."""
    p.add_argument(
        "--threads", type=int, help="torch CPU threads (default: the cores not already busy)"
    )


def check_threads(requested: int | None) -> None:
    """InputError unless ``--threads`` is unset or a positive count (checked before any work)."""
    from dronecap.errors import InputError

    if requested is not None and requested < 1:
        raise InputError(f"--threads takes a positive number of threads, got {requested}")
