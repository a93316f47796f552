"""The swarm's pieces of ``dronecap sfm`` that need no COLMAP run: a camera per drone, a folder
per drone in COLMAP's work folder, pose jumps per flight, which flights are linked."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.datasets.format import Dataset
from dronecap.errors import InputError
from dronecap.sfm.camera_plan import plan_camera
from dronecap.sfm.flights import flight_of, image_names
from dronecap.sfm.links import linked_groups
from dronecap.sfm.report import pose_jumps

CAM = Camera(120.0, 120.0, 80.0, 80.0, 160, 160, "OPENCV", (-0.1, 0.02, 0.0, 0.0))


def swarm_frames(cameras: list[Camera] | None, drones: list[int]) -> Dataset:
    ds = Dataset(images=np.zeros((len(drones), 160, 160, 1), np.uint8), kind="frames")
    ds.drone = np.asarray(drones, np.int16)
    ds.drone_names = [f"drone_{d}" for d in range(max(drones) + 1)]
    if cameras is not None:
        ds.set_cameras(cameras, ds.drone)
    return ds


def test_a_calibrated_swarm_keeps_every_drones_own_camera_fixed():
    other = dataclasses.replace(CAM, fx=123.0, fy=123.0)
    plan = plan_camera(swarm_frames([CAM, other], [0, 0, 1, 1]), "auto")
    assert plan.mode == "fixed" and plan.cameras == (CAM, other)
    (m0, p0), (m1, p1) = plan.colmap_per_drone()
    assert m0 == m1 == "OPENCV" and p0[0] == 120.0 and p1[0] == 123.0


def test_an_uncalibrated_swarm_estimates_a_camera_per_drone():
    plan = plan_camera(swarm_frames(None, [0, 1, 2]), "auto")
    assert plan.mode == "estimate" and plan.cameras == (None, None, None)
    assert plan.colmap_per_drone() == [None, None, None]
    estimate = plan_camera(swarm_frames([CAM, CAM], [0, 1, 1]), "estimate")
    assert [k.model for k in estimate.cameras] == ["SIMPLE_RADIAL"] * 2


def test_camera_from_is_refused_for_a_swarm(tmp_path):
    with pytest.raises(InputError, match="one drone's camera"):
        plan_camera(swarm_frames([CAM, CAM], [0, 1, 1]), "auto", tmp_path / "posed.h5")


def test_work_folder_names_put_each_drone_in_its_own_folder():
    assert image_names(np.zeros(3, np.int64)) == ["00000.png", "00001.png", "00002.png"]
    names = image_names(np.array([0, 0, 1, 2]))
    assert names == ["d00/00000.png", "d00/00001.png", "d01/00002.png", "d02/00003.png"]
    assert [flight_of(n) for n in names] == [0, 0, 1, 2] and flight_of("00007.png") == 0
    assert names == sorted(names)  # COLMAP's sequential pairs follow name order


def test_pose_jumps_are_found_within_each_flight_not_between_flights():
    line = np.stack([np.arange(6.0), np.zeros(6), np.zeros(6)], 1)
    far = line + [100.0, 0.0, 0.0]  # a second drone's flight, far away
    centres = np.concatenate([line, far])
    frames = np.arange(12)
    flights = np.repeat([0, 1], 6)
    assert pose_jumps(centres, frames, flights) == []
    bent = centres.copy()
    bent[8] += [0.0, 20.0, 0.0]  # drone 1's third frame leaves its path and comes back
    assert pose_jumps(bent, frames, flights) == [8]


def test_linked_groups_follow_chains_of_links_and_ignore_weak_ones():
    links = np.zeros((4, 4), np.int64)
    links[0, 1] = links[1, 0] = 40  # 0-1 and 1-2 overlap; 2-3 share two chance pairs
    links[1, 2] = links[2, 1] = 12
    links[2, 3] = links[3, 2] = 2
    assert linked_groups(links) == [[0, 1, 2], [3]]
    assert linked_groups(links, min_pairs=1) == [[0, 1, 2, 3]]
    assert linked_groups(np.zeros((2, 2), np.int64)) == [[0], [1]]
