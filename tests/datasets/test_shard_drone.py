"""`dronecap shard --scheme drone`: a shard per drone of its own train frames, own camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.cli import main
from dronecap.datasets.format import SPLITS, Dataset, open_dataset, write_dataset

TRAIN, TEST = SPLITS["train"], SPLITS["test"]


def swarm_dataset(path: Path, cv_lookat, drone: list[int], split: list[int]) -> Path:
    """Cameras on a circle looking at the origin, of three drones each with its own camera."""
    n = len(drone)
    az = np.linspace(0, 2 * np.pi, n, endpoint=False)
    eyes = 3 * np.stack([np.cos(az), np.sin(az), 0.2 * np.ones(n)], -1)
    ds = Dataset(
        images=np.zeros((n, 4, 4, 1), np.uint8),
        poses=np.stack([cv_lookat(e, np.zeros(3)) for e in eyes]),
        names=[f"v{i}" for i in range(n)],
        split=np.array(split, np.int8),
        aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
        drone=np.array(drone, np.int16),
        drone_names=["d0.mp4", "d1.mp4", "d2.mp4"],
    )
    ds.set_cameras([Camera(4.0 + d, 4.0 + d, 2.0, 2.0, 4, 4) for d in range(3)], ds.drone)
    return write_dataset(path, ds)


def test_one_shard_per_drone_with_its_own_frames_and_camera(
    tmp_path: Path, cv_lookat, capsys
) -> None:
    drone = [0, 0, 1, 1, 2, 2, 0, 1, 2, 0]
    split = [TRAIN] * 8 + [TEST] * 2
    src = swarm_dataset(tmp_path / "d.h5", cv_lookat, drone, split)
    out = tmp_path / "shards"
    assert main(["shard", str(src), "--scheme", "drone", "-o", str(out)]) == 0
    assert "of drone d2.mp4" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == [
        "client_0.h5", "client_1.h5", "client_2.h5", "summary.json",
    ]  # fmt: skip
    for d in range(3):
        sh = open_dataset(out / f"client_{d}.h5")
        own = sh.indices("train")
        assert (sh.drones()[own] == d).all()
        assert len(own) == sum(1 for i in range(8) if drone[i] == d)
        assert sorted(sh.extra["parent_index"][sh.indices("test")].tolist()) == [8, 9]
        assert all(sh.camera_of(int(i)).fx == 4.0 + d for i in own)
        assert {sh.camera_of(int(i)).fx for i in sh.indices("test")} == {6.0, 4.0}


def test_a_drone_without_train_frames_is_one_line_and_nothing_written(
    tmp_path: Path, cv_lookat, capsys
) -> None:
    drone = [0, 0, 1, 1, 2, 2, 0, 1, 2, 0]
    split = [TRAIN] * 4 + [TEST] * 2 + [TRAIN] * 2 + [TEST] * 2  # drone 2: only test frames
    src = swarm_dataset(tmp_path / "d.h5", cv_lookat, drone, split)
    out = tmp_path / "shards"
    assert main(["shard", str(src), "--scheme", "drone", "-o", str(out)]) != 0
    err = capsys.readouterr().err.strip()
    assert "'d2.mp4' has no train frame" in err and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("scheme", ["iid", "sector"])
def test_other_schemes_still_work_on_a_swarm(tmp_path: Path, cv_lookat, scheme: str) -> None:
    src = swarm_dataset(tmp_path / "d.h5", cv_lookat, [0, 1, 2] * 3 + [0], [TRAIN] * 8 + [TEST] * 2)
    assert (
        main(["shard", str(src), "--scheme", scheme, "--clients", "2", "-o", str(tmp_path / "s")])
        == 0
    )
