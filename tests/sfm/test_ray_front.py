"""How the Ray front end cuts flights into tasks and which pairs it leaves to the centre."""

from __future__ import annotations

import numpy as np

from dronecap.sfm.flights import image_names
from dronecap.sfm.ray_front import pieces, seam_pairs


def test_a_long_flight_is_cut_into_runs_and_a_short_tail_joins_the_last() -> None:
    names = image_names(np.zeros(340, np.int64))
    parts = pieces(names, 150)
    assert [len(p) for p in parts] == [150, 190]  # the 40-frame tail is under half a piece
    assert sum(parts, []) == names
    assert [len(p) for p in pieces(names, 100)] == [100, 100, 140]
    assert pieces(names[:30], 150) == [names[:30]]


def test_a_swarm_is_cut_per_drone_and_no_piece_mixes_drones() -> None:
    drones = np.repeat([0, 1, 2], [120, 40, 200])
    names = image_names(drones)
    parts = pieces(names, 100)
    assert [len(p) for p in parts] == [120, 40, 100, 100]
    for p in parts:
        assert len({n.split("/")[0] for n in p}) == 1


def test_seam_pairs_are_the_sequential_pairs_across_cuts_within_a_flight() -> None:
    drones = np.repeat([0, 1], [30, 30])
    names = image_names(drones)
    parts = pieces(names, 10)  # three pieces per drone
    seams = seam_pairs(parts, overlap=3)
    # each cut of a flight: frames 7-9 with 10-12 within 3 frames -> 3 + 2 + 1 pairs
    assert len(seams) == 2 * 2 * 6
    piece = {n: k for k, p in enumerate(parts) for n in p}
    index = {n: i for i, n in enumerate(names)}
    for a, b in seams:
        assert piece[a] != piece[b] and a.split("/")[0] == b.split("/")[0]
        assert 0 < index[b] - index[a] <= 3
    # the cut between the drones' flights is no seam: their frames are not a sequence
    assert (names[29], names[30]) not in seams
    # together with each piece's own sequential pairs, every sequential pair is matched once
    own = {
        (p[i], p[j]) for p in parts for i in range(len(p)) for j in range(i + 1, min(i + 4, len(p)))
    }
    every = {
        (names[i], names[j])
        for i in range(60)
        for j in range(i + 1, min(i + 4, 60))
        if drones[i] == drones[j]
    }
    assert own.isdisjoint(seams) and own | set(seams) == every
