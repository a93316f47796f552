"""Which drones' flights are linked, and keeping the unlinked ones out of the swarm's model.

Two flights are *linked* when at least :data:`MIN_LINK_PAIRS` pairs of their frames (one frame
from each) have a verified two-view geometry with at least :data:`LINK_INLIER_FACTOR` x
``min_num_matches`` inliers. The drones linked to the drone with most frames in the chosen model,
directly or through other drones, form the swarm's model; any other drone's frames are taken out
of it (the mapper's relaxed extension pass can place a few frames of an unrelated flight on
chance matches) and that drone's flight, with the drones linked to it, is mapped on its own into
``work/unlinked/dNN``: reported by name, never silently dropped or silently merged.

Why a stricter bar than mapping's: a pair of frames of two unrelated places can pass geometric
verification on a few repeated textures (a verified pair needs 15 inliers); several pairs with
twice that are what a real overlap between two flights gives (the simulated 4-drone corridor:
hundreds).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.colmap_steps import incremental_map
from dronecap.sfm.flights import flight_folder, flight_of
from dronecap.sfm.options import SfmOptions

MIN_LINK_PAIRS = 3  # frame pairs across two flights needed to call them linked
LINK_INLIER_FACTOR = 2  # x min_num_matches: inliers of a pair that counts as a link
UNLINKED = "unlinked"  # work-folder subfolder of the unlinked flights' own models


def flight_links(database: Path, n_drones: int, min_inliers: int) -> np.ndarray:
    """int [D, D]: verified frame pairs with at least ``min_inliers`` inliers between the
    flights of drones i and j (symmetric; the diagonal counts pairs within a flight)."""
    import pycolmap

    links = np.zeros((n_drones, n_drones), np.int64)
    with pycolmap.Database.open(database) as db:
        flight = {im.image_id: flight_of(im.name) for im in db.read_all_images()}
        pair_ids, geoms = db.read_two_view_geometries()
    for pair_id, g in zip(pair_ids, geoms, strict=True):
        if g.inlier_matches.shape[0] >= min_inliers:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            links[flight[a], flight[b]] += 1
            if flight[a] != flight[b]:
                links[flight[b], flight[a]] += 1
    return links


def linked_groups(links: np.ndarray, min_pairs: int = MIN_LINK_PAIRS) -> list[list[int]]:
    """The drones in groups linked directly or through each other (``links``: int [D, D] from
    :func:`flight_links`); every drone is in exactly one group, groups sorted by first drone."""
    n = len(links)
    group = list(range(n))

    def root(i: int) -> int:
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if links[i, j] >= min_pairs:
                group[root(j)] = root(i)
    out: dict[int, list[int]] = {}
    for i in range(n):
        out.setdefault(root(i), []).append(i)
    return sorted(out.values())


def separate_unlinked(
    database: Path,
    image_dir: Path,
    root: Path,
    model: Path,
    names: list[str],
    n_drones: int,
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
) -> tuple[str, dict[str, Any]]:
    """Keep only the drones linked to the chosen ``model``'s main drone in it; map every other
    group of linked drones on its own (see the module docstring).

    Returns the model folder to keep (``model``, or ``root/linked`` when frames were taken out)
    and the summary's "flights" record: the links matrix, the groups, the main group, and per
    other group its drones and its own model ({"drones", "model", "frames"}).
    """
    import pycolmap

    links = flight_links(database, n_drones, LINK_INLIER_FACTOR * opts.min_num_matches)
    groups = linked_groups(links)
    rec = pycolmap.Reconstruction(model)
    in_model = np.bincount(
        [flight_of(rec.images[i].name) for i in rec.reg_image_ids()], minlength=n_drones
    )
    main = next(g for g in groups if int(np.argmax(in_model)) in g)
    record: dict[str, Any] = {"links": links.tolist(), "groups": groups, "main": main}
    record["unlinked"] = []
    kept = str(model)
    strays = [i for i in rec.reg_image_ids() if flight_of(rec.images[i].name) not in main]
    if strays:
        for image_id in strays:
            rec.deregister_frame(rec.images[image_id].frame_id)
        kept = str(root / "linked")
        Path(kept).mkdir(parents=True, exist_ok=True)
        rec.write(kept)
        record["frames_taken_out"] = len(strays)
    for g in groups:
        if g == main:
            continue
        own = [n for n in names if flight_of(n) in g]
        out_dir = root / UNLINKED / "_".join(flight_folder(d) for d in g)
        found = incremental_map(
            database, image_dir, out_dir, opts, refine_camera, on_register, image_names=own
        )
        best = max(found, key=lambda k: found[k]["frames"], default=None)
        record["unlinked"].append(
            {
                "drones": g,
                "model": None if best is None else str(Path(best).relative_to(root)),
                "frames": 0 if best is None else int(found[best]["frames"]),
            }
        )
    return kept, record
