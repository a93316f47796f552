"""Shards for federated training: the train images of a dataset partitioned over K drones.

Three schemes:

- ``iid``: a seeded shuffle of the train images, cut into K parts whose sizes differ by at most 1;
- ``sector``: each drone gets a contiguous angular sector of viewpoints — the azimuth of the
  camera centre around the scene centre (the AABB's centre, or the cameras' common look-at
  point without one), measured about the scene's up axis (:func:`scene_up`: perpendicular to
  the cameras' horizontal x axes, on the side of their mean up vector). The circle is cut at
  the widest gap between neighbouring views, then into K runs of equal image counts, so some
  sides of the scene stay unseen by each drone (the paper's non-IID setup: lego, 4 drones x 25
  images);
- ``drone``: a real swarm's partition, what each drone saw: drone d's shard holds the train
  images of its own flight (the dataset's ``/drone``), with its own camera (K = the number of
  drones; ``clients`` is not used).

Each shard is a dataset file ``client_K.h5`` (kind "shard") holding that drone's train images plus
the common test set; ``shards/<scheme>`` marks each frame's client (-1 for test frames) and
``extra/parent_index`` its index in the source dataset. ``summary.json`` says which views went
where. The folder is written atomically.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.bounds import lookat_point
from dronecap.datasets.format import SPLITS, Dataset, open_dataset, provenance, write_dataset
from dronecap.errors import InputError, check_option
from dronecap.files import atomic_output, sha256_file

SCHEMES = ("iid", "sector", "drone")


def scene_up(poses: np.ndarray) -> np.ndarray:
    """The scene's up axis, from how the cameras are held.

    Cameras that do not roll keep their x axis horizontal, so up is the direction most nearly
    perpendicular to every camera's x axis: the eigenvectors of mean(x xᵀ) with eigenvalue
    < 0.1 span the candidates (one direction for cameras all around a scene, a plane for cameras
    that all face one way), and up is the mean camera up vector (-y in OpenCV axes) projected
    onto them. Without such directions (cameras rolled every way) it is that mean itself.

    Args:
        poses: float64 [N, 4, 4] camera-to-world, OpenCV axes.

    Returns:
        float64 [3] unit vector.
    """
    x = poses[:, :3, 0]
    mean_up = -poses[:, :3, 1].mean(0)
    w, v = np.linalg.eigh(x.T @ x / len(x))  # ascending eigenvalues
    basis = v[:, w < 0.1] if (w < 0.1).any() else np.eye(3)
    up = basis @ (basis.T @ mean_up)
    if np.linalg.norm(up) < 1e-9:
        up = v[:, 0]
    return up / np.linalg.norm(up)


def azimuths(centres: np.ndarray, origin: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Azimuth of points around ``origin`` about the axis ``up``.

    Args:
        centres: float [N, 3] points (camera centres).
        origin: float [3] the scene centre.
        up: float [3] unit axis.

    Returns:
        float64 [N] radians in [0, 2 pi), counter-clockwise seen from above, 0 along the world
        axis least aligned with ``up`` (projected onto the horizontal plane).
    """
    e1 = np.eye(3)[np.argmin(np.abs(up))]
    e1 = e1 - (e1 @ up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    r = centres - origin
    return np.mod(np.arctan2(r @ e2, r @ e1), 2 * np.pi)


def iid_assignment(n: int, clients: int, seed: int) -> np.ndarray:
    """Seeded shuffle of n items cut into ``clients`` parts (sizes differ by at most 1).

    Returns:
        int64 [n] client of each item.
    """
    perm = np.random.default_rng(seed).permutation(n)
    out = np.empty(n, np.int64)
    for k, part in enumerate(np.array_split(perm, clients)):
        out[part] = k
    return out


def sector_assignment(az: np.ndarray, clients: int) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous angular sectors with equal image counts.

    The views are ordered by azimuth, the circle is opened at the widest gap between neighbours,
    and the run is cut into ``clients`` parts whose sizes differ by at most 1.

    Args:
        az: float [n] azimuths in radians, [0, 2 pi).
        clients: number of sectors.

    Returns:
        (int64 [n] client of each view, float64 [clients, 2] each sector's (first, last) view
        azimuth in radians, counter-clockwise; last < first when the sector wraps past 0).
    """
    order = np.argsort(az, kind="stable")
    gaps = np.diff(np.r_[az[order], az[order[0]] + 2 * np.pi])
    order = np.roll(order, -(int(np.argmax(gaps)) + 1))  # start just after the widest gap
    out = np.empty(len(az), np.int64)
    ranges = np.empty((clients, 2))
    for k, part in enumerate(np.array_split(order, clients)):
        out[part] = k
        ranges[k] = az[part[0]], az[part[-1]]
    return out, ranges


def drone_count(ds: Dataset, train: np.ndarray, in_path: Path) -> int:
    """The number of drones D of ``ds`` (one shard each); every one must own train frames.

    Raises:
        InputError: a drone with no train frame (its shard would be empty), naming it.
    """
    drones = ds.drones()
    count = int(drones.max()) + 1 if ds.n else 0
    if ds.drone_names is not None:
        count = max(count, len(ds.drone_names))
    have = np.bincount(drones[train], minlength=count)
    for d in np.flatnonzero(have == 0):
        raise InputError(f"drone {ds.drone_name(int(d))!r} has no train frame to shard", in_path)
    return count


def shard_dataset(
    in_path: str | Path,
    out_dir: str | Path,
    clients: int,
    scheme: str,
    seed: int = 0,
) -> Path:
    """Partition a dataset's train images over ``clients`` drones; write one file per drone.

    Args:
        in_path: a dataset (kind "dataset") with poses and a split.
        out_dir: folder to write (replaced atomically): client_K.h5 files and summary.json. An
            existing folder holding anything else is refused, not replaced.
        clients: number of drones K >= 1 (scheme "drone": the dataset's drone count instead).
        scheme: "iid", "sector" or "drone".
        seed: seed of the iid shuffle (recorded for both schemes).

    Raises:
        InputError: unknown scheme, a negative seed, fewer train images than clients, no test
            images, no poses or split, or cameras with no azimuth spread around the up axis.
    """
    in_path, out_dir = Path(in_path), Path(out_dir)
    _check_arguments(out_dir, clients, scheme, seed)
    ds = open_dataset(in_path, kinds=("dataset",))
    if ds.poses is None:
        raise InputError("has no camera poses to shard by", in_path)
    if ds.split is None:
        raise InputError("has no train/test split (run `dronecap split` first)", in_path)
    train, test = ds.indices("train"), ds.indices("test")
    if not len(test):
        raise InputError("has no test frames: the drones' common test set would be empty", in_path)
    if scheme == "drone":
        clients = drone_count(ds, train, in_path)
    if len(train) < clients:
        raise InputError(
            f"{clients} clients need at least {clients} train images, found {len(train)}", in_path
        )
    centre = ds.aabb.mean(0) if ds.aabb is not None else lookat_point(ds.poses)
    up = scene_up(ds.poses[train])
    owner, ranges = _assign(ds, train, centre, up, clients, scheme, seed, in_path)
    digest = sha256_file(in_path)
    summary: dict[str, Any] = {
        "dataset": str(in_path),
        "dataset_sha256": digest,
        "scheme": scheme,
        "clients": clients,
        "seed": seed,
        "scene_centre": centre.tolist(),
        "up": up.tolist(),
        "test_views": [ds.frame_name(i) for i in test],
        "shards": [],
    }
    params = {"scheme": scheme, "clients": clients, "seed": seed}
    prov = provenance("shard", params, {in_path.name: digest})
    prov["parent"] = ds.provenance
    assignment = np.full(ds.n, -1, np.int16)
    assignment[train] = owner
    with atomic_output(out_dir, replaceable=SHARD_FILE.fullmatch) as tmp:
        tmp.mkdir()
        for k in range(clients):
            mine = train[owner == k]
            summary["shards"].append(_summary_entry(ds, k, mine, scheme, ranges))
            idx = np.sort(np.concatenate([mine, test]))
            shard = _shard(ds, idx, assignment, k, prov, in_path)
            write_dataset(tmp / f"client_{k}.h5", shard)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=1))
    return out_dir


def _check_arguments(out_dir: Path, clients: int, scheme: str, seed: int) -> None:
    """InputError for an unknown scheme, clients < 1, a negative seed, or an existing
    ``out_dir`` holding anything but shards."""
    if scheme not in SCHEMES:
        raise InputError(f"unknown shard scheme {scheme!r}: use one of {', '.join(SCHEMES)}")
    if clients < 1:
        raise InputError(f"clients must be at least 1, got {clients}")
    check_option("seed", seed, minimum=0)
    existing = sorted(p.name for p in out_dir.iterdir()) if out_dir.is_dir() else []
    if other := [name for name in existing if not SHARD_FILE.fullmatch(name)]:
        raise InputError(
            f"holds files that are not shards ({', '.join(other[:3])}): not replacing it", out_dir
        )


def _assign(
    ds: Dataset,
    train: np.ndarray,
    centre: np.ndarray,
    up: np.ndarray,
    clients: int,
    scheme: str,
    seed: int,
    in_path: Path,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The client of every train frame, int64 [len(train)], and (scheme "sector") each
    sector's azimuth range, float64 [clients, 2] radians (None for the other schemes)."""
    az = azimuths(ds.poses[train, :3, 3], centre, up)
    if not (np.isfinite(az).all() and np.isfinite(centre).all()):
        raise InputError("cameras give no finite azimuths around the scene centre", in_path)
    if scheme == "iid":
        return iid_assignment(len(train), clients, seed), None
    if scheme == "drone":
        return ds.drones()[train], None
    flat = ds.poses[train, :3, 3] - centre
    horizontal = np.linalg.norm(flat - np.outer(flat @ up, up), axis=1)
    if horizontal.max() <= 1e-9 * max(1.0, np.abs(flat).max()):
        raise InputError("cameras have no azimuth spread around the up axis", in_path)
    if (distinct := len(np.unique(np.round(az, 6)))) < clients:  # e.g. all at one point
        msg = f"cameras lie at {distinct} distinct azimuths: too few for {clients} sectors"
        raise InputError(f"{msg} (each would be 0 degrees wide)", in_path)
    return sector_assignment(az, clients)


def _summary_entry(
    ds: Dataset, k: int, mine: np.ndarray, scheme: str, ranges: np.ndarray | None
) -> dict[str, Any]:
    """``summary.json``'s record of client ``k`` holding train frames ``mine``."""
    entry: dict[str, Any] = {
        "client": k,
        "file": f"client_{k}.h5",
        "n_train": int(len(mine)),
        "views": [ds.frame_name(i) for i in mine],
        "parent_index": mine.tolist(),
    }
    if scheme == "drone":
        entry["drone"] = ds.drone_name(k)
    if ranges is not None:
        first, last = np.degrees(ranges[k])
        entry["azimuth_deg"] = [round(float(first), 3), round(float(last), 3)]
        entry["span_deg"] = round(float((last - first) % 360), 3)
    return entry


SHARD_FILE = re.compile(r"client_\d+\.h5|summary\.json")  # what a shard folder holds


def _shard(
    ds: Dataset,
    idx: np.ndarray,
    assignment: np.ndarray,
    client: int,
    prov: dict[str, Any],
    in_path: Path,
) -> Dataset:
    """The shard of ``client``: frames ``idx`` of ``ds`` with their assignment and provenance."""
    sub = ds.subset(idx)
    sub.split = np.where(assignment[idx] == client, SPLITS["train"], SPLITS["test"]).astype(np.int8)
    params = prov["params"]
    return dataclasses.replace(
        sub,
        kind="shard",
        shards={params["scheme"]: assignment[idx]},
        extra={"parent_index": idx},
        provenance=prov,
        attrs={**ds.attrs, **params, "client": client, "parent": in_path.name},
    )
