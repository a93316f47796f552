"""The key figure of each stage, read from the files the stage wrote (for summaries/reports).

The registry (:mod:`dronecap.registry`) names each stage's reader. Each reader is forgiving: a
stage whose output lacks the expected file yields "" rather than an
error, since the figure is a convenience, not part of the stage's contract.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dronecap import workspace as ws


def _json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def _find(stage_dir: Path, name: str) -> Path:
    """``stage_dir/name``, or the first file of that name below it."""
    direct = stage_dir / name
    return direct if direct.exists() else next(iter(sorted(stage_dir.rglob(name))), direct)


def _h5_frames(stage_dir: Path, name: str) -> str:
    import h5py

    path = _find(stage_dir, name)
    if not path.exists():
        return ""
    with h5py.File(path, "r") as f:
        return f"{f['images'].shape[0]} frames"


def ingest(stage_dir: Path) -> str:
    """Frames kept by ingest."""
    return _h5_frames(stage_dir, ws.FRAMES) + " kept"


def sfm(stage_dir: Path) -> str:
    """Registration rate and, with ground truth, pose accuracy."""
    rep = _json(_find(stage_dir, ws.SFM_REPORT))
    if not rep:
        return ""
    reg = rep.get("registration_rate")
    text = f"registered {reg:.0%}" if isinstance(reg, float) else ""
    gt = rep.get("accuracy") or {}
    if "ate_percent" in gt:
        text += f", ATE {gt['ate_percent']:.2f}% of extent"
    if "rot_median_deg" in gt:
        text += f", rotation {gt['rot_median_deg']:.2f}° median"
    drones = rep.get("drones") or []
    if drones:  # a swarm: how many drones are in the one model
        linked = sum(bool(d.get("linked")) for d in drones)
        text += f", {linked}/{len(drones)} drones in one model"
    return text


def train(stage_dir: Path) -> str:
    """Test PSNR/SSIM and the GAP9 verdict."""
    m = _json(_find(stage_dir, ws.METRICS)).get("test") or {}  # None: --no-eval
    text = f"PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.3f}" if "psnr" in m else ""
    cost = _json(_find(stage_dir, ws.COST))
    verdicts = cost.get("verdicts", {})
    if verdicts:
        fits = all(v.get("fits") for k, v in verdicts.items() if k in ("l1", "l2", "l3"))
        seconds = cost.get("latency", {}).get("train", 0.0)
        took = f"{seconds / 60:.0f} min" if seconds >= 120 else f"{seconds:.1f} s"
        text += f"; GAP9: {'fits' if fits else 'DOES NOT FIT'}, {took} to train"
    return text


def federate(stage_dir: Path) -> str:
    """The global model's last PSNR."""
    rounds = _json(_find(stage_dir, ws.ROUNDS))
    last = (rounds.get("rounds") or [{}])[-1] if isinstance(rounds, dict) else {}
    return f"global PSNR {last['psnr']:.2f} dB" if "psnr" in last else ""


def dataset(stage_dir: Path) -> str:
    """Frames in the dataset written."""
    return _h5_frames(stage_dir, ws.DATASET)


def shards(stage_dir: Path) -> str:
    """Shard files written."""
    return f"{len(list(stage_dir.rglob('client_*.h5')))} shards"


RESULT_FILES = (
    "report.md",
    ws.SFM_REPORT,
    "points.ply",
    ws.METRICS,
    ws.COMPARE,
    ws.ROUNDS,
)


def results_of(stage_dir: Path) -> list[Path]:
    """The files of a stage a person looks at first (reports, metrics, comparison images)."""
    return [p for name in RESULT_FILES for p in sorted(stage_dir.rglob(name))[:1]]


def key_figure(reader: Callable[[Path], str] | None, stage_dir: Path) -> str:
    """One short text with the stage's headline number ("" when there is none)."""
    try:
        return reader(stage_dir) if reader else ""
    except (OSError, KeyError, TypeError, ValueError):
        return ""
