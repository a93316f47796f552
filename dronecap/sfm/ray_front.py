"""A swarm's per-flight front end on Ray: each drone's features and own pairs as one Ray task.

``dronecap sfm --ray local`` (a Ray instance on this machine) or ``--ray ADDRESS`` (an existing
Ray cluster, e.g. ``ray://head:10001`` or ``auto``): every drone's flight is sent to a task
as PNG bytes with its camera; the task extracts SIFT (:func:`extract_finer_when_sparse`) and
matches the flight's own pairs (:func:`match`: sequential + its own loop index) into a COLMAP
database of its own, and returns that database's bytes. The merge stays central: the databases
are merged with ``pycolmap.Database.merge`` (images, cameras, keypoints, descriptors, matches
and verified geometries), then the cross-flight pairs and mapping run as without Ray. Nothing
travels through a shared file system, so the workers may be other machines. Ray is imported
only here, and only when ``--ray`` is given.
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path
from typing import Any

from dronecap.sfm.colmap_steps import extract_finer_when_sparse, match
from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import SfmOptions


def flight_task(
    names: list[str],
    pngs: list[bytes],
    camera: tuple[str, list[float]] | None,
    options: dict[str, Any],
) -> dict[str, Any]:
    """One flight's front end (runs on a Ray worker): the database bytes and the summary parts
    ("keypoints", "first_octave", "match")."""
    opts = SfmOptions(**options)
    with tempfile.TemporaryDirectory(prefix="dronecap_flight_") as tmp:
        root = Path(tmp)
        for name, data in zip(names, pngs, strict=True):
            path = root / "images" / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        db = root / "database.db"
        keypoints, octave = extract_finer_when_sparse(db, root / "images", names, opts, [camera])
        info = match(db, root, opts, len(names))
        return {
            "database": db.read_bytes(),
            "keypoints": keypoints,
            "first_octave": octave,
            "match": info,
        }


def front_end_on_ray(
    database: Path,
    image_dir: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
) -> tuple[dict[str, int], int, list[dict[str, Any]]]:
    """Run :func:`flight_task` for every drone on Ray (``opts.ray``: "local" or a cluster
    address) and merge the flights' databases into ``database``.

    Returns (image name -> keypoints, the finest first octave used, each flight's match info).
    """
    import pycolmap
    import ray

    started = not ray.is_initialized()
    if started:
        address = None if opts.ray == "local" else opts.ray
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(flight_task)
        per_flight = dataclasses.replace(opts, num_threads=1)
        futures = []
        for d in range(len(cameras)):
            mine = [n for n in names if flight_of(n) == d]
            pngs = [(image_dir / n).read_bytes() for n in mine]
            futures.append(task.remote(mine, pngs, cameras[d], per_flight.to_dict()))
        results = ray.get(futures)
    finally:
        if started:
            ray.shutdown()
    parts = []
    for d, r in enumerate(results):
        part = database.parent / f"flight_{d:02d}.db"
        part.write_bytes(r["database"])
        parts.append(part)
    if len(parts) == 1:
        shutil.copyfile(parts[0], database)
    merged = parts[0]
    for k, part in enumerate(parts[1:], start=1):
        out = database if k == len(parts) - 1 else database.parent / f"merged_{k:02d}.db"
        with (
            pycolmap.Database.open(merged) as a,
            pycolmap.Database.open(part) as b,
            pycolmap.Database.open(out) as m,
        ):
            pycolmap.Database.merge(a, b, m)
        merged = out
    keypoints = {n: k for r in results for n, k in r["keypoints"].items()}
    octave = min(r["first_octave"] for r in results)
    return keypoints, octave, [r["match"] for r in results]
