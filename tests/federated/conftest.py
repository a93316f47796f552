"""The federated tests reuse the trainer tests' analytic cube scene; Messages need a task; real
Flower runs start from lego shards (:func:`lego_run`) and stop their processes
(:func:`flower`)."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from flwr.supercore.task_identity import TaskIdentity

from dronecap.nerf.config import preset
from tests.nerf.conftest import cube_rgb, make_cube  # noqa: F401  (pytest fixtures)


@pytest.fixture
def server_task(monkeypatch):
    """The identity Flower gives a ServerApp's process (run 1, node 0, task 1): Messages need
    it."""
    monkeypatch.setattr(TaskIdentity, "_run_id", 1)
    monkeypatch.setattr(TaskIdentity, "_node_id", 0)
    monkeypatch.setattr(TaskIdentity, "_task_id", 1)


@pytest.fixture
def lego_run(lego_dir: Path, tmp_path: Path) -> Callable[..., Path]:
    """``lego_run(drones, **fields)``: lego imported and split into ``drones`` IID shards under
    ``tmp_path``, and the run folder ``tmp_path / "run"`` holding its settings: the ``test``
    preset, 8 pretraining steps, 4 local steps a round, one evaluation view and fp16 transfers,
    ``fields`` giving the rest (``rounds``, the compression, the faults). Returns the folder."""

    def make(drones: int, **fields: Any) -> Path:
        from dronecap.datasets.blender import import_blender
        from dronecap.datasets.shard import shard_dataset
        from dronecap.federated.state import FedSettings, save_settings

        h5 = import_blender(lego_dir, tmp_path / "dataset.h5", progress=False)
        shards = shard_dataset(h5, tmp_path / "shards", drones, "iid")
        run = tmp_path / "run"
        settings = FedSettings(
            shards=[str(shards / f"client_{k}.h5") for k in range(drones)],
            cfg=dataclasses.asdict(preset("test")),
            pretrain=8,
            local_steps=4,
            eval_views=1,
            transfer_dtype="fp16",
            **fields,
        )
        save_settings(run, settings)
        return run

    return make


class FlowerProcesses:
    """The long-running Flower commands (SuperLink, SuperNodes) a test starts."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, cmd: str, env: dict[str, str], log: Path | None = None) -> None:
        """Run ``cmd`` (its trailing ``&`` dropped; ``exec``, so the pid is Flower's) in its own
        process group, its output into ``log`` (default: discarded)."""
        self.procs.append(
            subprocess.Popen(
                "exec " + cmd.rstrip(" &"),
                shell=True,
                env=env,
                start_new_session=True,
                stdout=log.open("w") if log is not None else subprocess.DEVNULL,
                stderr=subprocess.STDOUT if log is not None else subprocess.DEVNULL,
            )
        )

    def stop(self) -> None:
        """SIGTERM to every process group started, then wait for each (60 s at most)."""
        for p in self.procs:
            os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            p.wait(timeout=60)
        self.procs = []


@pytest.fixture
def flower() -> Iterator[FlowerProcesses]:
    """Starts Flower processes for a test; those still running at its end are stopped."""
    procs = FlowerProcesses()
    yield procs
    procs.stop()
