"""The workspace convention: every stage finds its inputs by conventional names in one folder.

``dronecap ingest flight.mp4 && dronecap sfm && dronecap split && dronecap shard &&
dronecap train`` works with no other arguments because each stage reads and writes these names
inside the workspace (the current directory unless ``--workdir`` says otherwise). Every path can
still be given explicitly; an explicit relative path is taken relative to the current directory.
"""

from __future__ import annotations

from pathlib import Path

FRAMES = "frames.h5"  # ingest -> sfm
POSED = "posed.h5"  # sfm -> split
DATASET = "dataset.h5"  # split / import-blender -> shard, train
SHARDS = "shards"  # shard -> federate (one client_K.h5 per drone)
SFM_DIR = "sfm"  # sparse model, PLY, report beside posed.h5
TRAIN_RUN = "runs/train"  # train -> render, eval, cost
FEDERATE_RUN = "runs/federate"
TRANSFORMS = "transforms"  # export-transforms
FLIGHT_VIDEO = "flight.mp4"  # simulate
FLIGHT_INFO = "flight.json"  # simulate: the ground truth beside the video
CALIBRATION = "calib.json"  # calibrate -> ingest --intrinsics
COST = "cost.json"  # cost (and train, inside its run folder)
PARETO = "pareto.png"  # cost --search
SFM_REPORT = "report.json"  # sfm, inside SFM_DIR
METRICS = "metrics.json"  # train, inside its run folder
COMPARE = "compare.png"  # train: ground truth | render
ROUNDS = "rounds.json"  # federate


def resolve(workdir: str | Path | None, explicit: str | Path | None, default: str) -> Path:
    """Path of an input/output: ``explicit`` if given, else ``workdir / default``."""
    if explicit is not None:
        return Path(explicit)
    return Path(workdir or ".") / default
