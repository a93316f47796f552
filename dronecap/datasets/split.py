"""Train/test split of a posed flight: every k-th frame (in capture order) goes to test.

With the default k = 8 the frames at capture positions 0, 8, 16, ... are held out, so a flight
of N frames gives ceil(N / 8) test frames (the paper's 1954 frames -> 1709 train / 245 test).
A file that already carries a split (an imported scene with its official split) keeps it. A
swarm's file (several drones) is split drone by drone, each in its own capture order, so every
drone holds out one frame in k of its own flight.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dronecap.datasets.format import SPLITS, Dataset, open_dataset, provenance, write_dataset
from dronecap.errors import InputError
from dronecap.files import sha256_file


def every_kth_split(order: np.ndarray, every: int = 8) -> np.ndarray:
    """Split by capture order: the frame of rank r goes to test when r % every == 0.

    Args:
        order: int [N] capture position of each frame (e.g. source frame numbers); ties keep
            file order.
        every: hold out one frame in ``every``.

    Returns:
        int8 [N] with SPLITS values (0 train, 2 test).
    """
    rank = np.empty(len(order), np.int64)
    rank[np.argsort(order, kind="stable")] = np.arange(len(order))
    return np.where(rank % every == 0, SPLITS["test"], SPLITS["train"]).astype(np.int8)


def per_drone_split(ds: Dataset, every: int = 8) -> np.ndarray:
    """:func:`every_kth_split` of each drone's frames in its own capture order (``source_index``
    when the file has it, else file order): int8 [N] with SPLITS values."""
    order = ds.source_index if ds.source_index is not None else np.arange(ds.n)
    drones = ds.drones()
    split = np.empty(ds.n, np.int8)
    for d in np.unique(drones):
        mine = np.flatnonzero(drones == d)
        split[mine] = every_kth_split(order[mine], every)
    return split


def has_split(ds: Dataset) -> bool:
    """True when ``ds`` already assigns at least one frame to a split."""
    return ds.split is not None and bool((ds.split >= 0).any())


def split_dataset(in_path: str | Path, out_path: str | Path, every: int = 8) -> Path:
    """Read a posed file (or a dataset), give it a train/test split, write a dataset.

    Frames are ordered by ``source_index`` when the file has it, else by their order in the file.
    An input that already has a split keeps it (``every`` is then ignored and recorded as such).

    Raises:
        InputError: unreadable input, no poses, ``every`` < 2, or a split without train or test.
    """
    in_path = Path(in_path)
    if every < 2:
        raise InputError(f"every must be at least 2 (one test frame in every k), got {every}")
    ds = open_dataset(in_path, kinds=("posed", "dataset"))
    if ds.poses is None:
        raise InputError("has no camera poses (run `dronecap sfm` first)", in_path)
    kept = has_split(ds)
    if kept:
        split = ds.split
    else:
        split = per_drone_split(ds, every)
    for name in ("train", "test"):
        if not (split == SPLITS[name]).any():
            raise InputError(f"a split of {ds.n} frames leaves no {name} frame", in_path)
    prov = provenance(
        "split",
        {"every": None if kept else every, "kept_existing_split": kept},
        {in_path.name: sha256_file(in_path)},
    )
    prov["parent"] = ds.provenance
    out = dataclasses.replace(ds, kind="dataset", split=split, provenance=prov)
    return write_dataset(out_path, out)
