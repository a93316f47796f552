"""Keyframes of a dense flight: map the frames that moved, then register the others.

A slowly flown flight keeps many near-duplicate frames (ingest's coverage rule keeps one frame
every ``max_gap`` source frames even when the view barely changed): the 1954-frame corridor
flight's consecutive kept frames move 1.0 px (median of their matches), the same route flown
9x slower 0.39 px. The mapper then triangulates from near-zero baselines, its chunks' seeds hold
few points, and the model bends (docs/sfm.md "Session 19"), while every frame costs mapping time.

Here the mapper sees only *keyframes*: walking the flight in order, the next keyframe is the
furthest frame (within the sequential pairs, ``opts.overlap`` frames) whose verified matches
with the current keyframe moved at most ``opts.keyframe_flow`` pixels (median), or the next frame
when even it moved more (:func:`keyframes`). The keyframes are matched among themselves as the
sequential matcher pairs frames (:func:`match_keyframes`): on the 3901-frame flight, without
those pairs a keyframe shared matches with its next keyframe only, and a quarter of the flight
did not map. The other frames are then registered into the
keyframes' model, which stays as mapped, without bundle adjustment (:func:`register_rest`):
each needs only its 2D-3D matches to the keyframes' points, so the cost is linear in frames.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.colmap_steps import mapper_options, match_listed, write_model
from dronecap.sfm.options import SfmOptions

PAIR_FILE = "keyframe_pairs.txt"  # work-folder file of the keyframes' pairs
REST = "registered_rest"  # work-folder subfolder of the model with every frame registered
MIN_INLIERS = 30  # a pair with fewer verified matches cannot decide the step (unverified)


def choose_keyframes(
    database: Path, work: Path, usable: list[str], opts: SfmOptions
) -> tuple[list[str], dict[str, Any]]:
    """The frames to map of one flight's ``usable`` frames (flight order): its keyframes
    (:func:`keyframes` at ``opts.keyframe_flow`` px), matched among themselves
    (:func:`match_keyframes`), or ``usable`` itself when every frame is a keyframe. Also
    returns the report's record: keyframes, frames and the flow threshold."""
    flow = median_flow(database, usable, opts.overlap)
    keep = keyframes(flow, len(usable), opts.overlap, opts.keyframe_flow)
    record: dict[str, Any] = {
        "keyframes": len(keep),
        "frames": len(usable),
        "flow_px": opts.keyframe_flow,
    }
    if len(keep) == len(usable):
        return usable, record
    names = [usable[i] for i in keep]
    record["pairs"] = match_keyframes(database, work, names, opts)
    return names, record


def median_flow(database: Path, names: list[str], gap_max: int) -> dict[tuple[int, int], float]:
    """Median motion (px) of the verified matches of frames i and j = i+1..i+``gap_max`` of
    ``names`` (flight order), for the pairs with at least :data:`MIN_INLIERS` of them."""
    import pycolmap

    flow: dict[tuple[int, int], float] = {}
    with pycolmap.Database.open(database) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        keys = [ids[n] for n in names]
        points: dict[int, np.ndarray] = {}

        def xy(i: int) -> np.ndarray:
            if i not in points:
                points[i] = np.asarray(db.read_keypoints(keys[i]))[:, :2]
            return points[i]

        for i in range(len(names)):
            for j in range(i + 1, min(i + gap_max + 1, len(names))):
                if not db.exists_two_view_geometry(keys[i], keys[j]):
                    continue
                m = np.asarray(db.read_two_view_geometry(keys[i], keys[j]).inlier_matches)
                if len(m) >= MIN_INLIERS:
                    step = xy(i)[m[:, 0]] - xy(j)[m[:, 1]]
                    flow[i, j] = float(np.median(np.linalg.norm(step, axis=1)))
            points.pop(i - gap_max, None)
    return flow


def keyframes(flow: dict[tuple[int, int], float], n: int, gap_max: int, most: float) -> list[int]:
    """Indices of the keyframes among ``n`` frames in flight order: the first, then each time
    the furthest frame within ``gap_max`` whose median ``flow`` (px, :func:`median_flow`) from
    the current keyframe is at most ``most`` (the next frame when none is), and the last."""
    if n == 0:
        return []
    keep, k = [0], 0
    while k < n - 1:
        near = [j for j in range(k + 1, min(k + gap_max + 1, n)) if flow.get((k, j), 1e9) <= most]
        k = max(near, default=k + 1)
        keep.append(k)
    return keep


def match_keyframes(database: Path, work: Path, names: list[str], opts: SfmOptions) -> int:
    """Match each keyframe of ``names`` (flight order) with the ``opts.overlap`` keyframes after
    it, as the sequential matcher pairs frames (pairs matched before are skipped): without
    these a keyframe shares matches with its next keyframe only, and the keyframes' model
    holds short tracks. Returns the pairs listed."""
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 : i + 1 + opts.overlap]]
    pair_file = work / PAIR_FILE
    pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    match_listed(database, pair_file, opts)
    return len(pairs)


def register_rest(
    database: Path,
    model: Path,
    out_dir: Path,
    names: list[str],
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
) -> dict[str, dict[str, float]]:
    """Register the frames of ``names`` (flight order) missing from the keyframes' ``model``,
    one at a time, by their 2D-3D matches with the keyframes' points (COLMAP's absolute-pose
    estimation and refinement), adding no points and without bundle adjustment: the keyframes'
    model stays as mapped. Passes go forwards and backwards through the flight until one
    registers nothing. Triangulating each new frame's tracks as well let frames beyond the
    keyframes' points register, but they drifted (3901-frame flight, keyframes' model missing
    its ends: rotation error median 4.3 deg against 0.53 without); those frames are left to
    the caller's extension pass. The model goes to ``out_dir``; returns its record
    (:func:`dronecap.sfm.colmap_steps.write_model`)."""
    import pycolmap

    pipeline = mapper_options(opts, refine_camera)  # its thresholds for registration
    cache_opts = pycolmap.DatabaseCacheOptions()
    cache_opts.min_num_matches = opts.min_num_matches
    cache_opts.image_names = set(names)
    with pycolmap.Database.open(database) as db:
        cache = pycolmap.DatabaseCache.create(db, cache_opts)
        ids = {im.name: im.image_id for im in db.read_all_images()}
    rec = pycolmap.Reconstruction(model)
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    done = {rec.images[i].name for i in rec.reg_image_ids()}
    todo = [ids[n] for n in names if n not in done]
    forward = True
    while todo:
        left = []
        for image_id in todo if forward else todo[::-1]:
            if mapper.register_next_image(pipeline.mapper, image_id):
                on_register(1)
            else:
                left.append(image_id)
        if len(left) == len(todo):
            break
        todo, forward = sorted(left), not forward
    rec = mapper.reconstruction
    mapper.end_reconstruction(False)
    return write_model(rec, out_dir)
