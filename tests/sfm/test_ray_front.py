"""How the Ray front end cuts flights into tasks and which pairs it leaves to the centre."""

from __future__ import annotations

import numpy as np
import pytest

from dronecap.sfm.flights import image_names
from dronecap.sfm.options import SfmOptions
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


@pytest.mark.slow
def test_one_flight_in_pieces_on_a_local_ray_cluster_gives_the_local_model(demo_corridor, tmp_path):
    """`sfm --ray local --ray-piece-frames 40` on the demo corridor (124 kept frames): three
    piece tasks on two workers, seams and loops matched centrally; every sequential pair is
    matched once, and the model agrees with the local run's and with the truth."""
    from dronecap.datasets.format import open_dataset
    from dronecap.sfm.align import pose_accuracy
    from dronecap.sfm.pipeline import run_sfm

    def sfm(name: str, **overrides) -> dict:
        return run_sfm(
            demo_corridor / "frames.h5",
            tmp_path / name / "posed.h5",
            tmp_path / name / "sfm",
            SfmOptions(**overrides),
            demo_corridor / "flight.json",
            progress=False,
        )

    local, ray = sfm("local"), sfm("ray", ray="local", ray_piece_frames=40)
    on_ray = ray["matching"]["ray"]
    assert ray["matching"]["matcher"] == "pieces of flights (Ray tasks)"
    assert len(on_ray["pieces"]) == 3 and sum(on_ray["pieces"]) == local["frames_total"]
    assert on_ray["seam_pairs"] == 2 * sum(range(1, SfmOptions().overlap + 1))
    assert on_ray["loop_pairs"] > 0
    # each piece matches as the whole flight would (sequential), not as a short flight alone
    assert {p["matcher"] for p in on_ray["piece_matching"]} == {"sequential"}
    sequential = sum(p["matched_pairs"] for p in on_ray["piece_matching"]) + on_ray["seam_pairs"]
    assert sequential + on_ray["loop_pairs"] >= ray["matching"]["matched_pairs"] >= sequential
    for rep in (local, ray):
        assert rep["registration_rate"] >= 0.99
        assert rep["accuracy"]["ate_percent"] < 0.5 and not rep["bend_check"]["bent"]
    a, b = (
        open_dataset(tmp_path / "local" / "posed.h5"),
        open_dataset(tmp_path / "ray" / "posed.h5"),
    )
    both = sorted(set(a.source_index.tolist()) & set(b.source_index.tolist()))
    assert len(both) >= 0.99 * a.n
    pick = (
        [list(a.source_index).index(k) for k in both],
        [list(b.source_index).index(k) for k in both],
    )
    agree = pose_accuracy(b.poses[pick[1]], a.poses[pick[0]])
    assert agree.ate_percent < 0.5 and agree.rot_median_deg < 0.5


def test_a_ray_address_that_does_not_answer_is_refused_at_once() -> None:
    """Ray would retry an address nobody serves for minutes: sfm refuses it in one line."""
    import socket

    from dronecap.errors import InputError
    from dronecap.sfm.ray_front import check_address

    with socket.socket() as s:  # a port that was free a moment ago: nobody listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for bad in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}", "no-port", "host:abc"):
        with pytest.raises(InputError, match="--ray"):
            check_address(bad)
    for fine in ("", "local", "auto"):
        check_address(fine)
    with socket.socket() as s:  # a listening port passes
        s.bind(("127.0.0.1", 0))
        s.listen()
        check_address(f"127.0.0.1:{s.getsockname()[1]}")
