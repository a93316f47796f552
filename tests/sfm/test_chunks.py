"""Chunked mapping of long flights (issue 27): the partition, who gets chunked, and a real run
whose chunks are merged into one straight, accurate model."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest

from dronecap.datasets.format import write_dataset
from dronecap.sfm.blender_flight import blender_flight
from dronecap.sfm.chunks import (
    chunk_mapped,
    chunk_names,
    chunk_threads,
    keep_chunk_points,
    mapping_chains,
    merge_poses,
    start_chunk,
)
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.pipeline import run_sfm


def _names(n: int) -> list[str]:
    return [f"{i:05d}.png" for i in range(n)]


@pytest.mark.parametrize("n", [181, 200, 446, 1000, 4000])
def test_chunks_cover_the_flight_in_order_and_overlap_by_exactly_the_asked_frames(n):
    names = _names(n)
    chunks = chunk_names(names, 100, 20)
    assert chunks[0][0] == names[0] and chunks[-1][-1] == names[-1]
    assert sorted({f for c in chunks for f in c}) == names  # every frame, none invented
    for a, b in zip(chunks[:-1], chunks[1:], strict=True):
        assert a[-20:] == b[:20]  # the seed: the last 20 of one are the first 20 of the next
        assert set(a) & set(b) == set(b[:20])  # and nothing else is shared
    sizes = [len(c) for c in chunks]
    assert max(sizes) - min(sizes) <= 1  # no small tail chunk
    assert all(80 <= s <= 125 for s in sizes)


def test_a_flight_within_one_chunk_is_one_chunk_and_bad_overlaps_are_refused():
    assert chunk_names(_names(100), 100, 20) == [_names(100)]
    assert chunk_names(_names(30), 100, 20) == [_names(30)]
    for overlap in (0, 50, 60):
        with pytest.raises(ValueError):
            chunk_names(_names(300), 100, overlap)


def test_chunks_are_mapped_outwards_from_the_start_in_two_independent_chains():
    chains = mapping_chains([[]] * 5, 2)
    assert chains == [[(3, 2), (4, 3)], [(1, 2), (0, 1)]]
    for chain in chains:  # each chunk resumes from the start or from the one before it
        done = {2}
        for k, prev in chain:
            assert prev in done
            done.add(k)
    assert mapping_chains([[]] * 3, 0) == [[(1, 0), (2, 1)]]  # nothing before the first
    assert mapping_chains([[]], 0) == []


def test_the_start_chunk_is_the_one_nearest_the_middle_that_holds_a_pair():
    chunks = chunk_names(_names(300), 100, 20)  # 4 chunks: 0-89, 70-159, 140-229, 210-299
    assert len(chunks) == 4
    pairs = [((1, 2), {"frames": ["00075.png", "00085.png"]})]
    assert start_chunk(chunks, pairs) == 1  # in chunks 0 and 1: the one nearer the middle
    end = ((5, 6), {"frames": ["00010.png", "00015.png"]})  # the best pair, at one end
    assert start_chunk(chunks, [end]) == 0  # the only chunk holding a pair
    assert start_chunk(chunks, [end, *pairs]) == 1  # a later pair nearer the middle wins
    middle = ((7, 8), {"frames": ["00145.png", "00152.png"]})  # chunks 1 and 2, equally near
    assert start_chunk(chunks, [end, middle]) == 1  # a tie: the earlier chunk
    too_wide = ((3, 4), {"frames": ["00010.png", "00150.png"]})  # in no chunk
    assert start_chunk(chunks, [too_wide, end]) == 0
    assert start_chunk(chunks, [too_wide]) is None and start_chunk(chunks, []) is None
    long_flight = chunk_names(_names(4000), 150, 40)
    tail = ((9, 10), {"frames": ["03900.png", "03905.png"]})
    first = ((11, 12), {"frames": ["00100.png", "00106.png"]})
    k = start_chunk(long_flight, [tail, first, middle])
    chains = mapping_chains(long_flight, k)
    assert [len(c) for c in chains] == [len(long_flight) - 2, 1]  # only pairs near the ends
    centre = [f"{i:05d}.png" for i in (2000, 2006)]
    k = start_chunk(long_flight, [tail, first, ((13, 14), {"frames": centre})])
    assert abs(len(mapping_chains(long_flight, k)[0]) - len(mapping_chains(long_flight, k)[1])) <= 1


def test_a_chain_left_alone_gets_all_the_cores(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 8)
    assert [chunk_threads(n) for n in (2, 1, 0)] == [4, 8, 8]
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    assert chunk_threads(2) == 1


def test_a_chunk_counts_as_mapped_only_with_most_of_its_new_frames():
    """150 frames, 40 from the seed: 41 registered (one new frame) does not carry the chain on,
    the 129 of a chunk that lost a few does."""
    assert not chunk_mapped(41, 150, 40)
    assert not chunk_mapped(40, 150, 40)
    assert chunk_mapped(129, 150, 40) and chunk_mapped(150, 150, 40)
    assert chunk_mapped(95, 150, 40) and not chunk_mapped(94, 150, 40)  # half of the 110 new


def test_only_long_single_flights_are_chunked():
    opts = SfmOptions()
    assert opts.chunked(446, n_drones=1)
    assert not opts.chunked(opts.chunk_above, n_drones=1)  # today's path up to the threshold
    assert not opts.chunked(4000, n_drones=4)  # a swarm's flights share no chunk frames
    assert not SfmOptions(chunk_above=0).chunked(4000, n_drones=1)  # 0: never
    bad_ones = ({"chunk_overlap": 0}, {"chunk_overlap": 75}, {"chunk_ba_iterations": -1})
    for bad in (*bad_ones, {"chunk_workers": 0}, {"verify_min_trials": 0}):
        with pytest.raises(ValueError):
            SfmOptions(**bad).validate()


def test_the_chunks_mappers_use_the_chunk_bundle_adjustment_and_nothing_else_changes():
    opts = SfmOptions(chunk_ba_global_ratio=2.5, chunk_ba_global_max_iterations=7)
    chunked = opts.for_chunks()
    assert (chunked.ba_global_ratio, chunked.ba_global_max_iterations) == (2.5, 7)
    assert chunked.ba_prune_redundant == opts.chunk_ba_prune_redundant
    assert opts.ba_global_ratio == SfmOptions().ba_global_ratio  # the caller's options stay
    same = {k: v for k, v in chunked.to_dict().items() if not k.startswith("ba_global")}
    assert same == {k: v for k, v in opts.to_dict().items() if not k.startswith("ba_global")} | {
        "ba_prune_redundant": opts.chunk_ba_prune_redundant
    }
    with pytest.raises(ValueError):
        SfmOptions(chunk_ba_global_ratio=1.0).validate()


def _chunk_model(image_ids: list[int], tracks: list[list[int]]) -> pycolmap.Reconstruction:
    """A chunk's model: a camera looking down +z from x = image id, 4 keypoints per frame, and
    one point per track (track = image ids; the point is keypoint ``p`` of each, p its index)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 64, 64)
    )
    for i in image_ids:
        image = pycolmap.Image(
            name=f"{i:05d}.png", keypoints=[np.array([8.0 * k, 8.0]) for k in range(4)],
            camera_id=1, image_id=i,
        )  # fmt: skip
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(), [-float(i), 0.0, 0.0])
        )
    for p, track in enumerate(tracks):
        t = pycolmap.Track()
        t.add_elements([pycolmap.TrackElement(i, p) for i in track])
        rec.add_point3D(np.array([float(p), 0.0, 5.0]), t)
    return rec


def test_merged_chunks_keep_their_points_in_the_frames_they_posed(tmp_path):
    """Frame 3 is in both chunks and keeps chunk A's pose and points: B's point seen in 3 and 4
    loses frame 3 and, seen once, is dropped; B's point seen in 3, 4, 5 keeps 4 and 5."""
    a = _chunk_model([1, 2, 3], [[1, 2, 3], [2, 3]])
    b = _chunk_model([3, 4, 5], [[3, 4, 5], [3, 4]])
    merged, n = merge_poses([a, b])
    record = keep_chunk_points(merged, [a, b], tmp_path / "m")
    rec = pycolmap.Reconstruction(tmp_path / "m")
    assert n == 5 and record[str(tmp_path / "m")]["frames"] == 5
    tracks = sorted(sorted(e.image_id for e in p.track.elements) for p in rec.points3D.values())
    assert tracks == [[1, 2, 3], [2, 3], [4, 5]]
    seen_in_3 = [e.point2D_idx for p in rec.points3D.values() for e in p.track.elements
                 if e.image_id == 3]  # fmt: skip
    assert sorted(seen_in_3) == [0, 1]  # chunk A's keypoints only, each once


def test_a_chunked_lego_flight_is_one_straight_accurate_model(lego_dir, tmp_path):
    """36 lego views in 3 chunks of ~16 (6 shared): one merged model, every frame, accurate."""
    ds, gt = blender_flight(lego_dir, count=36)
    write_dataset(tmp_path / "frames.h5", ds)
    (tmp_path / "gt.json").write_text(json.dumps(gt))
    opts = SfmOptions(
        matcher="sequential",
        overlap=5,
        loop_pairs="none",
        chunk_above=20,
        chunk_frames=16,
        chunk_overlap=6,
        num_threads=2,
    )
    report = run_sfm(
        tmp_path / "frames.h5",
        tmp_path / "posed.h5",
        tmp_path / "sfm",
        opts,
        tmp_path / "gt.json",
        progress=False,
    )
    assert "chunked" in report["models"]  # the merged chunks' model, not a fallback
    assert (tmp_path / "sfm" / "work" / "chunks").is_dir()
    acc = report["accuracy"]
    assert acc["registration_rate"] >= 35 / 36
    assert acc["ate_percent"] < 2.0  # the unchunked 30-frame lego run's bound
    assert acc["rot_median_deg"] < 6.0
    assert not report["bend_check"]["bent"] and report["bend_check"]["pairs"] >= 25
    assert 0 < report["quality"]["mean_reprojection_error_px"] < 1.5
