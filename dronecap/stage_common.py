"""Settings shared by several stages (one definition each): torch threads, progress output."""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.stage import Settings, setting


@dataclass(kw_only=True)
class TorchSettings(Settings):
    """A stage that runs torch: how many CPU threads."""

    threads: int | None = setting(
        None, help="torch CPU threads (default: the cores not already busy)"
    )  # checked by dronecap.cpu.check_threads


@dataclass(kw_only=True)
class ProgressSettings(Settings):
    """A stage with a progress bar it can hide."""

    no_progress: bool = setting(False, help="no progress bar")
