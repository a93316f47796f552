"""Reopen a training run dir: its trainer (from the checkpoint) and its dataset."""

from __future__ import annotations

import json
from pathlib import Path

from dronecap.datasets.format import Dataset, open_dataset
from dronecap.errors import InputError

from .trainer import CHECKPOINT, METRICS, RUN_INFO, Trainer, _write_json


def open_run(run_dir: str | Path, dataset: str | Path | None = None) -> tuple[Trainer, Dataset]:
    """(trainer, dataset) of a run dir; ``dataset`` defaults to the one in ``run.json``."""
    run_dir = Path(run_dir)
    if not (run_dir / CHECKPOINT).exists():
        raise InputError("not a training run (no checkpoint.pt; run `dronecap train`)", run_dir)
    if dataset is None:
        info_path = run_dir / RUN_INFO
        if not info_path.exists():
            raise InputError("no run.json naming the dataset; pass --dataset", run_dir)
        dataset = json.loads(info_path.read_text())["dataset"]
    ds = open_dataset(dataset, kinds=("dataset", "shard"))
    trainer = Trainer.load(run_dir / CHECKPOINT)
    if ds.channels != trainer.scene.channels:
        raise InputError(
            f"has {ds.channels} channels but the run's model has {trainer.scene.channels}", dataset
        )
    return trainer, ds


def update_metrics(run_dir: str | Path, new: dict) -> dict:
    """Merge ``new`` into ``run_dir/metrics.json`` (created if absent); return the result."""
    path = Path(run_dir) / METRICS
    m = json.loads(path.read_text()) if path.exists() else {}
    m |= new
    _write_json(path, m)
    return m
