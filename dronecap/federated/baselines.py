"""Baselines of a federated run, on the same step budget: centralized and each drone alone.

Both train one model for ``N_pt + R * N_l`` steps (the coordinator's critical path in the
federated run: the x axis of the paper's curves) and are tested at the same marks as the global
model (after ``N_pt``, then every ``N_l`` steps) on the same test views:

- ``centralized``: on the union of every drone's train images (the upper bound);
- ``client_K``: on drone K's train images only.

Each baseline checkpoints at every mark (``RUN/baselines/<name>.pt``) and records its curve in
``RUN/baselines/curves.json`` (its own file, so baselines may train while the federation runs),
so an interrupted run resumes at its last mark; :func:`merge_curves` copies the curves into
``RUN/rounds.json`` under ``baselines``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from dronecap.datasets.format import Dataset
from dronecap.errors import InputError
from dronecap.federated.state import (
    FedSettings,
    load_rounds,
    save_rounds,
    test_split,
    train_split,
)
from dronecap.files import atomic_output


def union_train(paths: list[str]) -> Dataset:
    """The train frames of several shard files as one dataset (frames in shard order).

    Raises:
        InputError: a shard with other scene bounds than the first (not cut from one dataset:
            one model cannot hold both, and drones' models would map points differently).
    """
    parts = [train_split(p) for p in paths]
    first = parts[0]
    for path, part in zip(paths[1:], parts[1:], strict=True):
        same = part.aabb is not None and first.aabb is not None
        if not same or not np.array_equal(part.aabb, first.aabb):
            raise InputError(f"has other scene bounds than {Path(paths[0]).name}", path)
        if part.cameras != first.cameras:  # a swarm's shards share the dataset's camera table
            raise InputError(f"has another camera table than {Path(paths[0]).name}", path)

    def cat(name: str) -> np.ndarray | None:
        if getattr(first, name) is None:
            return None
        return np.concatenate([getattr(p, name) for p in parts])

    return dataclasses.replace(
        first,
        images=cat("images"),
        alpha=cat("alpha"),
        poses=cat("poses"),
        split=cat("split"),
        near_far=cat("near_far"),
        camera_index=cat("camera_index"),
        drone=cat("drone"),
        names=None,
        source_index=None,
        timestamps=None,
        shards={},
        extra={},
    )


def baseline_trainsets(s: FedSettings) -> dict[str, Dataset]:
    """name -> train set of every baseline (``centralized``, ``client_0`` ...)."""
    sets = {"centralized": union_train(s.shards)}
    sets.update({f"client_{k}": train_split(p) for k, p in enumerate(s.shards)})
    return sets


def marks(s: FedSettings) -> list[int]:
    """Step counts at which models are tested: N_pt, N_pt + N_l, ..., N_pt + R N_l."""
    return [s.pretrain + r * s.local_steps for r in range(s.rounds + 1)]


def run_baseline(
    run_dir: Path, s: FedSettings, name: str, train: Dataset, curve_marks: bool = True
) -> list[dict]:
    """Train (or resume) one baseline to the full budget; returns its curve.

    The curve is a list of ``{"steps", "psnr", "ssim"}``, one per mark (only the last one
    without ``curve_marks``), stored in ``rounds.json["baselines"][name]`` after every mark.
    """
    from dronecap.nerf.trainer import Trainer

    ckpt = Path(run_dir) / "baselines" / f"{name}.pt"
    curve = load_curves(run_dir).get(name, [])
    fresh = not curve or not ckpt.exists()
    trainer = Trainer(s.train_config(), train) if fresh else Trainer.load(ckpt, train=train)
    test = test_split(s.shards[0], s.eval_views)
    last = curve[-1]["steps"] if curve else -1
    for m in [m for m in (marks(s) if curve_marks else marks(s)[-1:]) if m > last]:
        trainer.train(max(m - trainer.step, 0))
        with atomic_output(ckpt) as tmp:
            trainer.save(tmp)
        metrics = trainer.evaluate(test)
        curve.append({"steps": m, "psnr": float(metrics["psnr"]), "ssim": float(metrics["ssim"])})
        curves = load_curves(run_dir)
        curves[name] = curve
        with atomic_output(_curves_file(run_dir)) as tmp:
            tmp.write_text(json.dumps(curves, indent=1))
    return curve


def run_baselines(
    run_dir: Path, s: FedSettings, curve_marks: bool = True, names: list[str] | None = None
) -> dict:
    """Run the baselines ``names`` in that order (default: centralized, then each drone alone);
    returns name -> curve."""
    sets = baseline_trainsets(s)
    return {n: run_baseline(run_dir, s, n, sets[n], curve_marks) for n in (names or list(sets))}


def merge_curves(run_dir: Path, s: FedSettings) -> None:
    """Copy the baselines' curves into ``RUN/rounds.json`` (key ``baselines``)."""
    save_rounds(run_dir, s, load_rounds(run_dir), baselines=load_curves(run_dir))


def _curves_file(run_dir: Path) -> Path:
    return Path(run_dir) / "baselines" / "curves.json"


def load_curves(run_dir: Path) -> dict[str, list[dict]]:
    """name -> curve of every baseline recorded in ``RUN/baselines/curves.json`` (empty when
    none); each curve a list of ``{"steps", "psnr", "ssim"}``."""
    p = _curves_file(run_dir)
    return dict(json.loads(p.read_text())) if p.exists() else {}
