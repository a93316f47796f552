"""Shards: determinism, coverage, the common test set, angular contiguity, impossible requests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.format import SPLITS, Dataset, open_dataset, write_dataset
from dronecap.datasets.shard import (
    azimuths,
    iid_assignment,
    scene_up,
    sector_assignment,
    shard_dataset,
)
from dronecap.errors import InputError

TRAIN, TEST = SPLITS["train"], SPLITS["test"]


def ring_dataset(path: Path, cv_lookat, az_deg: list[float], n_test: int = 2) -> Path:
    """Cameras on a horizontal circle of radius 3 looking at the origin, then n_test above it."""
    az = np.radians(az_deg + [45.0 * i for i in range(n_test)])
    eyes = 3 * np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], -1)
    eyes[len(az_deg) :, 2] = 1.0
    poses = np.stack([cv_lookat(e, np.zeros(3)) for e in eyes])
    n = len(az)
    ds = Dataset(
        images=np.zeros((n, 2, 2, 1), np.uint8),
        poses=poses,
        names=[f"v{i}" for i in range(n)],
        split=np.array([TRAIN] * len(az_deg) + [TEST] * n_test, np.int8),
        aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
    )
    return write_dataset(path, ds)


def test_up_and_azimuth_of_a_ring(cv_lookat) -> None:
    poses = np.stack([cv_lookat([3 * np.cos(a), 3 * np.sin(a), 0], np.zeros(3)) for a in (0, 2)])
    np.testing.assert_allclose(scene_up(poses), [0, 0, 1], atol=1e-12)
    # up = +z: azimuth 0 along +x, counter-clockwise towards +y
    pts = np.array([[1.0, 0, 5], [0, 2, -1], [-1, 0, 0], [0, -1, 0]])
    np.testing.assert_allclose(
        azimuths(pts, np.zeros(3), np.array([0, 0, 1.0])), np.pi / 2 * np.arange(4)
    )


def test_up_ignores_how_cameras_are_spread(cv_lookat) -> None:
    # level cameras (no roll) at uneven elevations and azimuths, all on one side: their mean up
    # vector leans towards the centre, but their x axes are all horizontal
    rng = np.random.default_rng(2)
    az, el = rng.uniform(0, 2, 30), rng.uniform(0.1, 1.3, 30)
    eyes = 3 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    poses = np.stack([cv_lookat(e, np.zeros(3)) for e in eyes])
    assert (
        np.degrees(np.arccos(-poses[:, 2, 1].mean() / np.linalg.norm(poses[:, :3, 1].mean(0)))) > 5
    )
    np.testing.assert_allclose(scene_up(poses), [0, 0, 1], atol=1e-9)
    # cameras all facing one way (x axes parallel): up is their mean up vector
    fwd = np.stack([cv_lookat([0, -3, h], [0, 0, h + 0.3]) for h in (0.0, 0.5, 1.0)])
    np.testing.assert_allclose(
        scene_up(fwd), -fwd[:, :3, 1].mean(0) / np.linalg.norm(fwd[:, :3, 1].mean(0))
    )


def test_iid_is_seeded_and_even() -> None:
    a, b, c = iid_assignment(10, 3, 7), iid_assignment(10, 3, 7), iid_assignment(10, 3, 8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert sorted(np.bincount(a).tolist()) == [3, 3, 4]


def test_sectors_by_hand() -> None:
    az = np.radians([10, 20, 30, 100, 110, 120, 200, 210, 220, 350])
    owner, ranges = sector_assignment(az, 3)
    # widest gap 220 -> 350 opens the circle: 350, 10, 20, 30 | 100, 110, 120 | 200, 210, 220
    assert owner.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 0]
    np.testing.assert_allclose(np.degrees(ranges), [[350, 30], [100, 120], [200, 220]])


def test_sector_shard_files(tmp_path: Path, cv_lookat) -> None:
    src = ring_dataset(
        tmp_path / "d.h5", cv_lookat, [10, 20, 30, 100, 110, 120, 200, 210, 220, 350]
    )
    out = shard_dataset(src, tmp_path / "shards", clients=3, scheme="sector", seed=5)
    summary = json.loads((out / "summary.json").read_text())
    assert [s["views"] for s in summary["shards"]] == [
        ["v0", "v1", "v2", "v9"],
        ["v3", "v4", "v5"],
        ["v6", "v7", "v8"],
    ]
    assert (
        summary["shards"][0]["azimuth_deg"] == [350, 30] and summary["shards"][0]["span_deg"] == 40
    )
    assert summary["test_views"] == ["v10", "v11"]
    s0 = open_dataset(out / "client_0.h5", kinds=("shard",))
    assert s0.names == ["v0", "v1", "v2", "v9", "v10", "v11"]
    assert s0.split.tolist() == [TRAIN] * 4 + [TEST] * 2
    assert s0.shards["sector"].tolist() == [0, 0, 0, 0, -1, -1]
    assert s0.extra["parent_index"].tolist() == [0, 1, 2, 9, 10, 11]
    assert (s0.attrs["scheme"], s0.attrs["client"], s0.attrs["clients"], s0.attrs["seed"]) == (
        "sector",
        0,
        3,
        5,
    )
    np.testing.assert_array_equal(s0.poses, open_dataset(src).poses[[0, 1, 2, 9, 10, 11]])


def test_rerun_replaces_the_whole_folder(tmp_path: Path, cv_lookat) -> None:
    src = ring_dataset(tmp_path / "d.h5", cv_lookat, [0, 60, 120, 180, 240, 300])
    shard_dataset(src, tmp_path / "shards", clients=3, scheme="iid")
    shard_dataset(src, tmp_path / "shards", clients=2, scheme="iid")
    assert sorted(p.name for p in (tmp_path / "shards").iterdir()) == [
        "client_0.h5",
        "client_1.h5",
        "summary.json",
    ]


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("scheme", "unknown shard scheme"),
        ("too_many", "5 clients need at least 5 train images, found 4"),
        ("zero", "at least 1"),
        ("no_split", "no train/test split"),
        ("same_azimuth", "no azimuth spread"),
    ],
)
def test_impossible_requests_write_nothing(
    tmp_path: Path, cv_lookat, case: str, message: str
) -> None:
    src = ring_dataset(tmp_path / "d.h5", cv_lookat, [0, 90, 180, 270])
    clients, scheme = 2, "sector"
    if case == "scheme":
        scheme = "by-colour"
    elif case == "too_many":
        clients = 5
    elif case == "zero":
        clients = 0
    elif case == "no_split":
        ds = open_dataset(src)
        ds.split = None
        write_dataset(src, ds)
    else:  # train cameras whose up is +y, all on the y axis through the centre: no azimuth
        ds = open_dataset(src)
        ds.poses[:4, :3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
        ds.poses[:4, :3, 3] = [[0, i + 2.0, 0] for i in range(4)]
        write_dataset(src, ds)
    with pytest.raises(InputError) as err:
        shard_dataset(src, tmp_path / "shards", clients=clients, scheme=scheme)
    assert "\n" not in str(err.value) and message in str(err.value)
    assert not (tmp_path / "shards").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5"]


@pytest.fixture(scope="module")
def lego_shards(lego_h5: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """lego sharded 4 ways by both schemes."""
    root = tmp_path_factory.mktemp("lego_shards")
    return {
        s: shard_dataset(lego_h5, root / s, clients=4, scheme=s, seed=1) for s in ("iid", "sector")
    }


@pytest.mark.parametrize("scheme", ["iid", "sector"])
def test_lego_coverage_and_common_test_set(
    lego_h5: Path, lego_shards: dict[str, Path], scheme: str
) -> None:
    parent = open_dataset(lego_h5)
    seen = []
    for k in range(4):
        s = open_dataset(lego_shards[scheme] / f"client_{k}.h5", kinds=("shard",))
        mine = s.extra["parent_index"][s.split == TRAIN]
        assert len(mine) == 25
        seen += mine.tolist()
        # the common test set, whole, in every shard
        np.testing.assert_array_equal(
            s.extra["parent_index"][s.split == TEST], parent.indices("test")
        )
        np.testing.assert_array_equal(s.images, parent.images[s.extra["parent_index"]])
    assert sorted(seen) == parent.indices("train").tolist()  # each train image exactly once


def test_lego_sectors_are_contiguous(lego_h5: Path, lego_shards: dict[str, Path]) -> None:
    parent = open_dataset(lego_h5)
    summary = json.loads((lego_shards["sector"] / "summary.json").read_text())
    train = parent.indices("train")
    owner = np.full(parent.n, -1)
    for s in summary["shards"]:
        owner[s["parent_index"]] = s["client"]
    az = azimuths(
        parent.poses[train, :3, 3], np.array(summary["scene_centre"]), np.array(summary["up"])
    )
    around = owner[train][np.argsort(az)]
    # walking once around the circle, the client changes exactly 4 times: 4 contiguous sectors
    assert int((around != np.roll(around, 1)).sum()) == 4
    # the up axis derived from the cameras is Blender's +z
    np.testing.assert_allclose(summary["up"], [0, 0, 1], atol=1e-3)


def test_iid_shards_are_deterministic(
    lego_h5: Path, lego_shards: dict[str, Path], tmp_path: Path
) -> None:
    again = shard_dataset(lego_h5, tmp_path / "again", clients=4, scheme="iid", seed=1)
    first = json.loads((lego_shards["iid"] / "summary.json").read_text())["shards"]
    second = json.loads((again / "summary.json").read_text())["shards"]
    assert [s["views"] for s in first] == [s["views"] for s in second]


def test_cli_defaults(lego_h5: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "dataset.h5").symlink_to(lego_h5)
    assert main(["shard", "--workdir", str(tmp_path)]) == 0
    assert capsys.readouterr().out.count("25 train views") == 4
    assert (tmp_path / "shards" / "client_3.h5").exists()
    assert (
        main(["shard", "--workdir", str(tmp_path), "--scheme", "rings", "-o", str(tmp_path / "x")])
        == 1
    )
    assert "rings" in capsys.readouterr().err and not (tmp_path / "x").exists()
