"""The front end on Ray: features and sequential pairs of a flight's pieces as Ray tasks.

``dronecap sfm --ray local`` (a Ray instance on this machine) or ``--ray ADDRESS`` (an existing
Ray cluster, e.g. ``ray://head:10001`` or ``auto``). Every flight (one, or each drone's of a
swarm) is cut into pieces of ``opts.ray_piece_frames`` consecutive frames (:func:`pieces`). Each
piece goes to a task as PNG bytes with its drone's camera; the task extracts SIFT
(:func:`extract_finer_when_sparse`) and matches and verifies the piece's own sequential pairs in
a COLMAP database of its own, and returns keypoints, descriptors, matches and verified
geometries as arrays (:func:`piece_task`). Nothing travels through a shared file system, so the
workers may be other machines.

The rest stays central (:func:`front_end_on_ray`): the images are imported into one database
with the cameras a local run would give them (one per drone), the tasks' arrays are written
into it, and the pairs no task could see are matched here: the sequential pairs that straddle
two pieces of a flight (:func:`seam_pairs`) and the flights' loop pairs (our bag of words,
:func:`dronecap.sfm.retrieval.write_loop_pairs`, whatever ``opts.loop_pairs`` says); a swarm's
cross-flight pairs follow in :func:`dronecap.sfm.colmap_steps.match`. Ray is imported only here,
and only when ``--ray`` is given.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.colmap_steps import match, match_listed
from dronecap.sfm.features import extract_finer_when_sparse, import_images
from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.retrieval import write_loop_pairs

REACH_TIMEOUT = (
    5.0  # s: a Ray cluster's address must answer within this (else Ray retries for minutes)
)


def check_address(address: str) -> None:
    """Raise InputError unless a TCP connection to the Ray cluster ``address`` ("HOST:PORT" or
    "ray://HOST:PORT") opens within :data:`REACH_TIMEOUT`; "" (no Ray), "local" (started here)
    and "auto" (Ray's own lookup, which fails at once) pass. Ray itself keeps retrying an
    address that does not answer for minutes."""
    import socket

    from dronecap.errors import InputError

    if address in ("", "local", "auto"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"--ray {address}: give 'local', 'auto', HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=REACH_TIMEOUT).close()
    except OSError as err:
        raise InputError(f"--ray {address}: no Ray cluster answers there ({err})") from None


def pieces(names: list[str], size: int) -> list[list[str]]:
    """``names`` (flight order) cut into runs of ``size`` consecutive frames of one flight
    each; a flight's last run shorter than ``size / 2`` joins the one before it."""
    out: list[list[str]] = []
    for d in sorted({flight_of(n) for n in names}):
        mine = [n for n in names if flight_of(n) == d]
        runs = [mine[a : a + size] for a in range(0, len(mine), size)]
        if len(runs) > 1 and len(runs[-1]) < size / 2:
            tail = runs.pop()
            runs[-1] = runs[-1] + tail
        out += runs
    return out


def seam_pairs(parts: list[list[str]], overlap: int) -> list[tuple[str, str]]:
    """The sequential pairs (each frame with its next ``overlap`` frames of its own flight)
    whose frames lie in different ``parts``: the pairs no piece task matched."""
    piece = {n: k for k, p in enumerate(parts) for n in p}
    out = []
    for d in sorted({flight_of(n) for n in piece}):
        mine = sorted(n for n in piece if flight_of(n) == d)
        for i, a in enumerate(mine):
            out += [(a, b) for b in mine[i + 1 : i + 1 + overlap] if piece[b] != piece[a]]
    return out


def piece_task(
    names: list[str],
    pngs: list[bytes],
    camera: tuple[str, list[float]] | None,
    options: dict[str, Any],
) -> dict[str, Any]:
    """One piece's front end (runs on a Ray worker), as arrays.

    Returns "keypoints" {name: float32 [K, 6]}, "descriptors" {name: uint8 [K, 128]},
    "matches" [(name1, name2, uint32 [M, 2])], "geometries" [(name1, name2,
    TwoViewGeometry.todict())], "first_octave" and "match" (the piece's match summary)."""
    import pycolmap

    opts = dataclasses.replace(SfmOptions(**options), loop_detection=False)
    with tempfile.TemporaryDirectory(prefix="dronecap_piece_") as tmp:
        root = Path(tmp)
        for name, data in zip(names, pngs, strict=True):
            path = root / "images" / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        db_path = root / "database.db"
        _, octave = extract_finer_when_sparse(db_path, root / "images", names, opts, [camera])
        info = match(db_path, root, opts, len(names))
        with pycolmap.Database.open(db_path) as db:
            images = {im.image_id: im.name for im in db.read_all_images()}
            keypoints = {n: db.read_keypoints(i) for i, n in images.items()}
            descriptors = {n: np.asarray(db.read_descriptors(i).data) for i, n in images.items()}
            pair_ids, matches = db.read_all_matches()
            geo_ids, geometries = db.read_two_view_geometries()

    def named(pair_id: int) -> tuple[str, str]:
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        return images[a], images[b]

    return {
        "keypoints": keypoints,
        "descriptors": descriptors,
        "matches": [(*named(p), m) for p, m in zip(pair_ids, matches, strict=True)],
        "geometries": [(*named(p), g.todict()) for p, g in zip(geo_ids, geometries, strict=True)],
        "first_octave": octave,
        "match": {k: v for k, v in info.items() if k != "verified_partners"},
    }


def front_end_on_ray(
    database: Path,
    image_dir: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
) -> tuple[dict[str, int], int, dict[str, Any]]:
    """Run :func:`piece_task` for every piece on Ray (``opts.ray``: "local" or a cluster
    address), write the results into ``database`` and match the seam and loop pairs here.

    Returns (image name -> keypoints, the finest first octave used, a summary: pieces, their
    frames and match summaries, seam and loop pairs and the seconds spent on them here)."""
    import ray

    parts = pieces(names, opts.ray_piece_frames)
    started = not ray.is_initialized()
    if started:
        address = None if opts.ray == "local" else opts.ray
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(piece_task)
        # the matcher the whole job resolves to (a short piece alone would match exhaustively)
        matcher = opts.resolved_matcher(len(names))
        per_piece = dataclasses.replace(opts, num_threads=1, matcher=matcher).to_dict()
        futures = [
            task.remote(p, [(image_dir / n).read_bytes() for n in p], cameras[flight_of(p[0])],
                        per_piece)
            for p in parts
        ]  # fmt: skip
        results = ray.get(futures)
    finally:
        if started:
            ray.shutdown()
    import_images(database, image_dir, names, cameras)
    _write_results(database, results)
    summary: dict[str, Any] = {
        "pieces": [len(p) for p in parts],
        "piece_matching": [r["match"] for r in results],
    }
    _match_between_pieces(database, parts, opts, summary)
    keypoints = {n: len(k) for r in results for n, k in r["keypoints"].items()}
    return keypoints, min(r["first_octave"] for r in results), summary


def _write_results(database: Path, results: list[dict[str, Any]]) -> None:
    """Write the tasks' keypoints, descriptors, matches and geometries into ``database``
    (images imported already), by image name."""
    import pycolmap

    sift = pycolmap.FeatureExtractorType.SIFT
    with pycolmap.Database.open(database) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for r in results:
            for name, kp in r["keypoints"].items():
                db.write_keypoints(ids[name], np.asarray(kp, np.float32))
                db.write_descriptors(
                    ids[name], pycolmap.FeatureDescriptors(sift, r["descriptors"][name])
                )
            for a, b, m in r["matches"]:
                db.write_matches(ids[a], ids[b], m)
            for a, b, g in r["geometries"]:
                db.write_two_view_geometry(ids[a], ids[b], pycolmap.TwoViewGeometry(g))


def _match_between_pieces(
    database: Path, parts: list[list[str]], opts: SfmOptions, summary: dict[str, Any]
) -> None:
    """Match and verify, in ``database``, the :func:`seam_pairs` of ``parts`` and the loop
    pairs of every flight (when ``opts`` asks for loops); fills ``summary``."""
    t = time.perf_counter()
    pair_file = database.parent / "between_pieces_pairs.txt"
    seams = seam_pairs(parts, opts.overlap)
    pair_file.write_text("".join(f"{a} {b}\n" for a, b in seams))
    summary["seam_pairs"] = len(seams)
    if opts.loop_detection and opts.loop_pairs != "none":
        loops = database.parent / "loop_pairs.txt"
        summary["loop_pairs"] = write_loop_pairs(
            database, loops, opts.loop_period, opts.loop_num_images, opts.overlap + 1, opts.seed
        )
        with pair_file.open("a") as f:
            f.write(loops.read_text())
    if pair_file.stat().st_size:
        match_listed(database, pair_file, opts)
    summary["between_pieces_seconds"] = round(time.perf_counter() - t, 3)
