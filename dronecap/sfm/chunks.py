"""Chunked mapping of a long flight: the mapper's global bundle adjustments stay chunk-sized.

COLMAP's incremental mapper re-adjusts the whole model every time it grew by a factor
(``ba_global_ratio``): on a long flight those global adjustments of an ever larger model are most
of the mapping time (446 kept frames: 497 of 616 s, mapping CPU growing with exponent 2.3,
benchmarks/results/sfm_scaling.md). Here the kept frames are cut, in flight order, into chunks of
``opts.chunk_frames`` frames overlapping by ``opts.chunk_overlap`` (:func:`chunk_names`). The chunk
nearest the middle of the flight that holds one of our initial pairs is mapped first, from its
best pair (:func:`start_chunk`); every other chunk, walking outwards from it, is mapped by
resuming from its already mapped neighbour reduced to their shared frames (the *seed*), whose
frames the mapper holds fixed: the chunk needs no initial pair of its own and lands in its
neighbour's coordinate frame (seed frames move by 1e-15). The chunks' mappers adjust globally
less often than an unchunked flight's (``SfmOptions.for_chunks``). The chunks after the start
chunk and those before it are two independent chains, mapped in two threads
(``opts.chunk_workers``; the same models as one after another), the cores shared among the
chains still mapping (:func:`chunk_threads`). The chunks' poses are then put into one model
(:func:`merge_poses`: a frame keeps the pose of the first chunk that registered it). By default
(``opts.chunk_ba_iterations`` 0, since session 19) the merged model keeps the chunks' own points
(:func:`keep_chunk_points`): the seeds already hold every chunk in its neighbour's frame, and
on the 446-frame corridor the merge took 0.3 instead of 26 CPU-s at ATE 0.214 vs 0.200 %,
rotation 0.30 vs 0.37 deg. With iterations > 0 (:func:`adjust_merged`) its points are
triangulated again from the database with those poses, and ONE bundle adjustment of the whole
model refines poses and points (the re-triangulated points' tracks cross the chunk boundaries:
keeping each chunk's own points instead, the adjustment moved nothing, ATE 0.57 -> 0.57 %).

Measured on the 446-frame corridor (benchmarks/results/sfm_scaling.md, docs/sfm.md "Chunked
mapping"): seeds freed, the chunks drift apart (ATE 0.64 %, rotation median 2.9 deg after the
merge); 100-frame chunks sharing 20 left one chunk bent on its own (rotation 2.85 deg) and the
final adjustment cannot straighten it (0.38 % / 0.56 deg at 10 and at 30 iterations); 150-frame
chunks sharing 40 (the default) give 0.20 % / 0.36 deg on the same database. The final
adjustment keeps COLMAP's solver choice (sparse Schur up to 1000 frames): iterative Schur needed
60 iterations (59 CPU-s) for what 10 sparse ones (26 CPU-s) reach; 4 sparse ones reach nearly
the same (0.189 vs 0.188 %, 9 CPU-s; ``opts.chunk_ba_iterations``).

A swarm (several drones) is never chunked: chunks of two drones' flights share no frames.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import shutil
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from dronecap.sfm.colmap_steps import (
    incremental_map,
    map_from_pairs,
    mapper_options,
    write_model,
)
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.wide_pairs import start_pairs

CHUNKS = "chunks"  # work-folder subfolder of the chunks' models
MERGED = "chunked"  # work-folder subfolder of the merged model
MIN_NEW_SHARE = 0.5  # a chunk is mapped when it registered this share of its non-seed frames
MIN_TRI_ANGLE = 1.5  # deg: a merged point seen under less is dropped (COLMAP's filter default)


def chunk_names(names: list[str], size: int, overlap: int) -> list[list[str]]:
    """Cut ``names`` (one flight, in flight order) into chunks of about ``size`` frames, each
    sharing its first ``overlap`` frames with the previous chunk's last ones.

    The chunks are as equal as possible (no small tail chunk: its frames are spread over the
    others). A flight of at most ``size`` frames is one chunk. Raises ValueError when
    ``overlap`` is not in [1, size / 2).
    """
    if not 1 <= overlap < size / 2:
        raise ValueError(f"chunk overlap must be in [1, {size / 2:g}), got {overlap}")
    n = len(names)
    step = size - overlap
    count = max(1, round((n - overlap) / step))
    if count == 1:
        return [list(names)]
    stride = (n - overlap) / count  # new frames per chunk, fractional
    bounds = [round(k * stride) for k in range(count + 1)]
    return [names[bounds[k] : bounds[k + 1] + overlap] for k in range(count)]


def mapping_chains(chunks: list[list[str]], start: int) -> list[list[tuple[int, int]]]:
    """The chunks to map after ``start`` as independent chains of (chunk, neighbour it resumes
    from): the chunks after ``start`` in flight order, then the ones before it walking back;
    each chain grows from ``start`` and shares nothing with the other (empty chains left out)."""
    after = [(k, k - 1) for k in range(start + 1, len(chunks))]
    before = [(k, k + 1) for k in range(start - 1, -1, -1)]
    return [c for c in (after, before) if c]


def seed_model(model: Path, shared: set[str], out: Path) -> Path:
    """Write to ``out`` the model at ``model`` with only the ``shared`` frames registered (the
    start of the next chunk's mapping); returns ``out``."""
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    for image_id in list(rec.reg_image_ids()):
        if rec.images[image_id].name not in shared:
            rec.deregister_frame(rec.images[image_id].frame_id)
    out.mkdir(parents=True, exist_ok=True)
    rec.write(out)
    return out


def map_chunks(
    database: Path,
    image_dir: Path,
    work: Path,
    chunks: list[list[str]],
    start: tuple[int, Path],
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
) -> list[Path | None]:
    """Map every chunk but the ``start`` one (chunk index, its model folder), each resumed
    from its neighbour's seed, the :func:`mapping_chains` in up to ``opts.chunk_workers``
    threads (pycolmap's mapper releases the GIL), the cores shared among the chains still
    mapping when a chunk starts. Each chain but the first maps from its own copy of the
    database: two mappers opening one SQLite file at the same moment can fail ("No registered
    database factory succeeded", seen in the test suite). Returns each chunk's model folder, in
    chunk order; None for a chunk that could not be mapped (nor the ones beyond it in its
    chain)."""
    models: list[Path | None] = [None] * len(chunks)
    models[start[0]] = start[1]
    chains = mapping_chains(chunks, start[0])
    workers = min(opts.chunk_workers, len(chains))
    lock = threading.Lock()
    running = [workers]  # chains still mapping: each new chunk gets the cores / this many

    def registered(k: int) -> None:
        with lock:  # one event at a time from either chain
            on_register(k)

    databases = [database] + [
        _copy(database, work / CHUNKS / f"chain{i}.db") for i in range(1, workers)
    ]

    def run(chain: list[tuple[int, int]], database: Path) -> None:
        for k, prev in chain:
            if models[prev] is None:
                break
            mine = opts
            if workers > 1 and opts.num_threads < 1:  # all cores, shared among the chains
                with lock:
                    mine = dataclasses.replace(opts, num_threads=chunk_threads(running[0]))
            models[k] = _map_chunk(
                database, image_dir, work, chunks[k], chunks[prev], k, models[prev], mine,
                refine_camera, registered,
            )  # fmt: skip
        with lock:
            running[0] -= 1

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        list(pool.map(run, chains, itertools.cycle(databases)))
    for copy in databases[1:]:
        copy.unlink()
    return models


def _copy(database: Path, to: Path) -> Path:
    """A copy of the COLMAP ``database`` at ``to`` (one chain's own)."""
    to.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(database, to)
    return to


def chunk_threads(chains: int) -> int:
    """COLMAP threads of a chunk mapped while ``chains`` chains (this one included) are
    mapping: the cores shared among them, so the chain left alone gets them all."""
    return max(1, (os.cpu_count() or 1) // max(1, chains))


def _map_chunk(
    database: Path,
    image_dir: Path,
    work: Path,
    names: list[str],
    neighbour: list[str],
    k: int,
    neighbour_model: Path,
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
) -> Path | None:
    """Map chunk ``k`` (frames ``names``) resumed from the seed of its mapped neighbour (frames
    ``neighbour``, model ``neighbour_model``); its model folder, or None unless
    :func:`chunk_mapped`."""
    shared = set(names) & set(neighbour)
    seed = seed_model(neighbour_model, shared, work / CHUNKS / f"seed{k:03d}")
    found = incremental_map(
        database,
        image_dir,
        work / CHUNKS / f"c{k:03d}",
        opts,
        refine_camera,
        on_register,
        input_path=seed,
        image_names=names,
        seeded=True,
    )
    best = max(found, key=lambda j: found[j]["frames"], default=None)
    mapped = best is not None and chunk_mapped(found[best]["frames"], len(names), len(shared))
    return Path(best) if mapped else None


def chunk_mapped(registered: int, frames: int, shared: int) -> bool:
    """Whether a chunk of ``frames`` frames whose mapper registered ``registered`` of them (its
    ``shared`` seed frames included) counts as mapped: at least :data:`MIN_NEW_SHARE` of its
    frames beyond the seed. A chunk that added a frame or two leaves the next chunk a seed
    without the frames they share (empty); that chunk's mapper then starts a model of its own,
    in another coordinate frame, which the merge took as aligned (the 3901-frame flight of
    session 19: chunks of 41 frames, ATE 11 %, docs/sfm.md "Session 19")."""
    return registered - shared >= MIN_NEW_SHARE * (frames - shared)


def merge_poses(models: list[Any]) -> tuple[Any, int]:
    """One reconstruction holding every registered frame of the chunk ``models``
    (pycolmap.Reconstruction, one coordinate frame), without points: a frame keeps its pose in
    the first model that has it. Returns it and the number of frames."""
    import pycolmap

    merged = pycolmap.Reconstruction()
    for rec in models:
        for cam_id, cam in rec.cameras.items():
            if not merged.exists_camera(cam_id):
                merged.add_camera_with_trivial_rig(cam)
        for image_id in rec.reg_image_ids():
            if merged.exists_image(image_id):
                continue
            im = rec.images[image_id]
            keypoints = [p.xy for p in im.points2D]
            fresh = pycolmap.Image(
                name=im.name, keypoints=keypoints, camera_id=im.camera_id, image_id=image_id
            )
            merged.add_image_with_trivial_frame(fresh, im.cam_from_world())
    return merged, merged.num_reg_images()


def adjust_merged(
    merged: Any,
    database: Path,
    image_dir: Path,
    out: Path,
    opts: SfmOptions,
    refine_camera: bool,
) -> dict[str, dict[str, float]]:
    """Triangulate the ``merged`` poses' points again from ``database`` (poses held), then one
    bundle adjustment of poses and points (COLMAP's solver choice, at most
    ``opts.chunk_ba_iterations`` iterations; camera refined when ``refine_camera``, never its
    principal point). Writes the model to ``out``; returns {folder: frames, reprojection px}."""
    import pycolmap

    out.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.triangulate_points(
        merged,
        database,
        image_dir,
        out,
        clear_points=True,
        options=mapper_options(opts, refine_camera),
        refine_intrinsics=refine_camera,
    )
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = ba.refine_extra_params = refine_camera
    ba.refine_principal_point = False
    ba.ceres.solver_options.max_num_iterations = opts.chunk_ba_iterations
    ba.ceres.solver_options.num_threads = opts.num_threads
    _drop_bad_points(rec, opts)
    pycolmap.bundle_adjustment(rec, ba)
    _drop_bad_points(rec, opts)
    return write_model(rec, out)


def keep_chunk_points(merged: Any, models: list[Any], out: Path) -> dict[str, dict[str, float]]:
    """The ``merged`` poses (:func:`merge_poses` of ``models``, same order) with the chunks'
    own points, neither triangulated again nor adjusted: each point keeps the observations in
    the frames whose pose came from its chunk (a frame's keypoints then belong to one chunk's
    points only), and is dropped when fewer than two remain. Writes the model to ``out``;
    returns {folder: frames, reprojection px}."""
    import pycolmap

    owner: dict[int, int] = {}
    for k, rec in enumerate(models):
        for image_id in rec.reg_image_ids():
            owner.setdefault(image_id, k)
    for k, rec in enumerate(models):
        for point in rec.points3D.values():
            kept = [e for e in point.track.elements if owner.get(e.image_id) == k]
            if len(kept) >= 2:
                track = pycolmap.Track()
                track.add_elements(kept)
                merged.add_point3D(point.xyz, track, point.color)
    merged.update_point_3d_errors()
    return write_model(merged, out)


def _drop_bad_points(rec: Any, opts: SfmOptions) -> None:
    """Delete ``rec``'s points observed with more than ``opts.max_reproj_error`` px, seen
    under less than COLMAP's 1.5 deg triangulation angle, or behind a camera."""
    import pycolmap

    manager = pycolmap.ObservationManager(rec)
    manager.filter_all_points3D(opts.max_reproj_error, MIN_TRI_ANGLE)
    manager.filter_observations_with_negative_depth()


def start_chunk(chunks: list[list[str]], pairs: list[tuple[Any, dict[str, Any]]]) -> int | None:
    """The chunk nearest the middle of the flight that holds both frames of one of our initial
    ``pairs`` (:func:`dronecap.sfm.initial_pair.initial_pairs`: every one passes the pair
    checks; a pair may lie further apart than the chunks overlap and fit in none), or None when
    none fits. From the middle, the two chains of :func:`mapping_chains` are about as long
    (the 3901-frame flight of session 13 started from its best pair's chunk, 26 of 33: one
    chain of 26 chunks, mostly alone on the cores)."""
    fits = {
        k for _, record in pairs for k, c in enumerate(chunks) if set(record["frames"]) <= set(c)
    }
    middle = (len(chunks) - 1) / 2
    return min(fits, key=lambda k: (abs(k - middle), k), default=None)


def chunked_map(
    database: Path,
    image_dir: Path,
    root: Path,
    chunks: list[list[str]],
    start: tuple[int, Path],
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
) -> tuple[dict[str, dict[str, float]], dict[str, Any]]:
    """The chunks after the ``start`` one (index, model folder) mapped (:func:`map_chunks`),
    merged (:func:`merge_poses`) and adjusted (:func:`adjust_merged`) into ``root/chunked``.

    Returns the merged model ({folder: frames, reprojection px}) and the report's record:
    frames per chunk, frames registered per chunk (0: not mapped) and merged."""
    import pycolmap

    t = time.process_time()
    models = map_chunks(
        database, image_dir, root, chunks, start, opts.for_chunks(), refine_camera, on_register
    )
    loaded = {k: pycolmap.Reconstruction(m) for k, m in enumerate(models) if m is not None}
    merged, n_merged = merge_poses(list(loaded.values()))
    t_merge = time.process_time()
    if opts.chunk_ba_iterations > 0:
        found = adjust_merged(merged, database, image_dir, root / MERGED, opts, refine_camera)
    else:
        found = keep_chunk_points(merged, list(loaded.values()), root / MERGED)
    record = {
        "frames": [len(c) for c in chunks],
        "registered": [
            loaded[k].num_reg_images() if k in loaded else 0 for k in range(len(chunks))
        ],
        "start": start[0],
        "merged": n_merged,
        "cpu_seconds": {
            "chunks": round(t_merge - t, 2),
            "adjust": round(time.process_time() - t_merge, 2),
        },
    }
    return found, record


def map_in_chunks(
    out: dict[str, Any],
    root: Path,
    usable: list[str],
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
    tiny: float,
) -> dict[str, dict[str, float]]:
    """Chunked mapping of one flight's ``usable`` frames (work folder ``root``), started from our
    pairs in the :func:`start_chunk` (nearest the middle). Returns the merged model, or {}
    (then the caller maps incrementally) when that start registers under ``tiny`` x its
    chunk's frames; fills ``out``'s init_pair and chunks (the report's records)."""
    db, images = root / "database.db", root / "images"
    chunks = chunk_names(usable, opts.chunk_frames, opts.chunk_overlap)
    pairs, info = start_pairs(db, root, opts, chunks[(len(chunks) - 1) // 2])
    k = start_chunk(chunks, pairs)
    out["chunks"] = {"frames": [len(c) for c in chunks], "start": k}
    mine = [p for p in pairs if k is not None and set(p[1]["frames"]) <= set(chunks[k])]
    enough = tiny * len(chunks[k or 0])
    found, tried = map_from_pairs(
        db, images, root / CHUNKS / "start", opts.for_chunks(), refine_camera, on_register, mine,
        enough, chunks[k or 0],
    )  # fmt: skip
    out["init_pair"] = {**info, "tried": tried, "chosen": tried[-1] if tried else None}
    best = max(found, key=lambda j: found[j]["frames"], default=None)
    if best is None or found[best]["frames"] < enough:
        return {}
    start = (k or 0, Path(best))
    found, out["chunks"] = chunked_map(
        db, images, root, chunks, start, opts, refine_camera, on_register
    )
    return found
