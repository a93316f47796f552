"""A swarm end to end on real files: `simulate --drones 2` -> `ingest` (a swarm folder, or one
source per drone) -> frames.h5 with a drone and a camera per frame -> (ground-truth poses) ->
`split` -> `shard --scheme drone` -> `train` on a shard with two cameras; bad swarms refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.format import open_dataset, write_dataset
from dronecap.simulator.simulate import Capture
from dronecap.simulator.swarm import SPREAD, drone_capture, drone_part

FRAMES = 16


@pytest.fixture(scope="session")
def swarm(tmp_path_factory) -> Path:
    """Two clean drones of 16 frames each over the corridor (mp4 per drone)."""
    out = tmp_path_factory.mktemp("swarm") / "swarm"
    argv = ["-q", "simulate", "--drones", "2", "--frames", str(FRAMES), "-o", str(out)]
    assert main(argv) == 0
    return out


@pytest.fixture(scope="session")
def swarm_frames(swarm: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ingest") / "frames.h5"
    assert main(["-q", "ingest", str(swarm), "-o", str(out)]) == 0
    return out


def test_each_drone_flies_its_own_overlapping_part_with_its_own_camera(swarm: Path) -> None:
    doc = json.loads((swarm / "swarm.json").read_text())
    assert [d["entry"] for d in doc["drones"]] == ["drone_0.mp4", "drone_1.mp4"]
    gts = [json.loads((swarm / d["ground_truth"]).read_text()) for d in doc["drones"]]
    fx = [g["intrinsics"]["fx"] for g in gts]
    assert fx[0] != fx[1] and all(abs(f / 120.0 - 1) <= 2 * SPREAD["focal"] for f in fx)
    # one world frame: drone 0 starts the corridor, drone 1 ends it, their parts overlap
    x = [np.array([f["c2w"][0][3] for f in g["frames"]]) for g in gts]
    assert x[0].min() < x[1].min() and x[0].max() < x[1].max() and x[0].max() > x[1].min()
    assert drone_part(0, 2, "corridor") == (0.0, 0.65)
    assert drone_part(1, 4, "orbit")[0] < 0.25 < drone_part(0, 4, "orbit")[1]
    a, b = drone_capture(Capture(), 0, 0), drone_capture(Capture(), 0, 0)
    assert a == b and a != drone_capture(Capture(), 1, 0)  # seeded, and per seed


def test_ingest_of_a_swarm_folder_gives_a_drone_and_a_camera_per_frame(
    swarm: Path, swarm_frames: Path
) -> None:
    ds = open_dataset(swarm_frames)
    doc = json.loads((swarm / "swarm.json").read_text())
    assert ds.drone_names == ["drone_0", "drone_1"] and ds.intrinsics is None
    assert set(ds.drones().tolist()) == {0, 1}
    assert [k.fx for k in ds.cameras] == [d["intrinsics"]["fx"] for d in doc["drones"]]
    for d in (0, 1):
        mine = ds.drones() == d
        assert (ds.camera_index[mine] == d).all()
        assert ds.source_index[mine].min() == 0  # indices in the drone's own video
        assert all(n.startswith(f"drone_{d}:") for n, m in zip(ds.names, mine, strict=True) if m)
    assert len(set(ds.names)) == ds.n


def test_ingest_of_one_source_per_drone_matches_the_folder(
    swarm: Path, swarm_frames: Path, tmp_path: Path
) -> None:
    out = tmp_path / "f.h5"
    videos = [str(swarm / "drone_0.mp4"), str(swarm / "drone_1.mp4")]
    assert main(["-q", "ingest", *videos, "-o", str(out)]) == 0
    a, b = open_dataset(out), open_dataset(swarm_frames)
    np.testing.assert_array_equal(a.images, b.images)
    assert a.cameras == b.cameras and a.names == b.names


def _folder(path: Path, images: list[np.ndarray]) -> Path:
    path.mkdir()
    for i, im in enumerate(images):
        cv2.imwrite(str(path / f"{i:04d}.png"), im)
    return path


@pytest.mark.parametrize("case", ["mixed", "duplicate", "unusable", "intrinsics-count"])
def test_bad_swarms_are_one_line_and_write_nothing(
    swarm: Path, tmp_path: Path, capsys, case: str
) -> None:
    video = str(swarm / "drone_0.mp4")
    black = str(_folder(tmp_path / "black", [np.zeros((64, 64), np.uint8)] * 6))
    argv, message = {
        "mixed": ([video, black], "sources of different kinds mixed"),
        "duplicate": ([video, video], "is given twice"),
        "unusable": ([str(swarm / "drone_1.mp4"), video, "--intrinsics", "none"], None),
        "intrinsics-count": ([video, str(swarm / "drone_1.mp4"), "--intrinsics", "1,1,1,1",
                              "--intrinsics", "2,2,2,2", "--intrinsics", "3,3,3,3"],
                             "--intrinsics given 3 times for 2 drones"),
    }[case]  # fmt: skip
    if case == "unusable":
        other = _folder(tmp_path / "other", [np.zeros((64, 64), np.uint8)] * 6)
        argv, message = [black, str(other)], "black"
    out = tmp_path / "frames.h5"
    assert main(["ingest", *argv, "-o", str(out)]) != 0
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not out.exists()


@pytest.mark.slow
def test_swarm_split_shard_by_drone_and_train_on_two_cameras(
    swarm: Path, swarm_frames: Path, tmp_path: Path
) -> None:
    """Ground-truth poses stand in for SfM (helper-independent): split per drone, a shard per
    drone, then a few training steps on a shard whose test views have both cameras."""
    ds = open_dataset(swarm_frames)
    doc = json.loads((swarm / "swarm.json").read_text())
    poses = []
    for d, i in zip(ds.drones(), ds.source_index, strict=True):
        gt = json.loads((swarm / doc["drones"][d]["ground_truth"]).read_text())
        poses.append(np.array(gt["frames"][int(i)]["c2w"]))
    ds.poses, ds.kind = np.stack(poses), "posed"
    ds.aabb = np.array([[-0.5, -1.0, 0.0], [3.5, 1.0, 2.0]])
    posed = write_dataset(tmp_path / "posed.h5", ds)
    dataset, shards = tmp_path / "dataset.h5", tmp_path / "shards"
    assert main(["-q", "split", str(posed), "-o", str(dataset), "--every", "4"]) == 0
    split = open_dataset(dataset)
    for d in (0, 1):  # every drone holds out one frame in 4 of its own flight
        assert (split.split[split.drones() == d] == 2).sum() == -(-(split.drones() == d).sum() // 4)
    assert main(["-q", "shard", str(dataset), "--scheme", "drone", "-o", str(shards)]) == 0
    shard = open_dataset(shards / "client_1.h5")
    assert (shard.drones()[shard.indices("train")] == 1).all()
    assert set(shard.camera_index[shard.indices("test")].tolist()) == {0, 1}
    run = tmp_path / "run"
    argv = ["train", str(shards / "client_1.h5"), "--preset", "test", "--steps", "5"]
    assert main([*argv, "--out", str(run), "--no-progress", "--threads", "1"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["steps"] == 5 and np.isfinite(metrics["test"]["psnr"])
    shutil.rmtree(run)
