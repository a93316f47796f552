"""Wide pairs matched for the start of a dense flight (sfm/wide_pairs.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from dronecap.sfm.blender_flight import blender_flight
from dronecap.sfm.features import extract
from dronecap.sfm.flights import image_names
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.wide_pairs import WIDE_ANCHORS, WIDE_GAPS, start_pairs, wide_pairs


def test_wide_pairs_spread_anchors_and_stay_inside_the_frames():
    names = [f"{i:05d}.png" for i in range(150)]
    pairs = wide_pairs(names)
    anchors = sorted({a for a, _ in pairs})
    assert len(anchors) == WIDE_ANCHORS and anchors[0] == names[0]
    gaps = {int(b[:5]) - int(a[:5]) for a, b in pairs}
    assert gaps == set(WIDE_GAPS)  # the first anchor has every partner inside 150 frames
    assert all(b in names for _, b in pairs)
    assert wide_pairs(names[: WIDE_GAPS[0]]) == []  # no frame has a partner that far
    few = wide_pairs(names[:20])
    assert few and all(int(b[:5]) - int(a[:5]) == WIDE_GAPS[0] for a, b in few)
    swarm = image_names(np.repeat([0, 1], 20))  # two drones' flights, one after the other
    paired = wide_pairs(swarm)
    assert paired and all(a.split("/")[0] == b.split("/")[0] for a, b in paired)


def test_narrow_starts_get_wide_pairs_matched_and_good_ones_do_not(lego_dir, tmp_path):
    """40 lego views matched only with their 3 neighbours: asked for a start angle no pair
    reaches, the wide pairs are matched into the database (and searched); at the default angle
    the flight's own pairs suffice and nothing is added."""
    ds, _ = blender_flight(lego_dir, count=40)
    (tmp_path / "images").mkdir()
    names = [f"{i:05d}.png" for i in range(ds.n)]
    for n, im in zip(names, ds.images, strict=True):
        cv2.imwrite(str(tmp_path / "images" / n), im[..., 0])
    k = ds.intrinsics
    opts = SfmOptions(num_threads=1, overlap=3)
    db = tmp_path / "db.db"
    extract(db, tmp_path / "images", names, opts, [("PINHOLE", [k.fx, k.fy, k.cx, k.cy])])
    sequential = pycolmap.SequentialPairingOptions(overlap=3, quadratic_overlap=False)
    pycolmap.match_sequential(db, pairing_options=sequential, device=pycolmap.Device.cpu)

    _, info = start_pairs(db, tmp_path, SfmOptions(num_threads=1), names)
    assert info["wide_pairs"] == 0

    _, info = start_pairs(db, tmp_path, SfmOptions(num_threads=1, init_min_tri_angle=80.0), names)
    assert info["wide_pairs"] == len(wide_pairs(names)) > 0
    with pycolmap.Database.open(db) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        assert all(d.exists_matches(ids[a], ids[b]) for a, b in wide_pairs(names))
