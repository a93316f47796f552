"""A camera and a drone per frame (format_version 3): round trip, subsets, validation, and
files of versions 1 and 2 reading as one camera and drone 0."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.datasets.format import Dataset, DatasetError, open_dataset, write_dataset

W, H = 6, 4


def two_drones() -> Dataset:
    """Four 6x4 frames of two drones, each with its own camera."""
    rng = np.random.default_rng(1)
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 2, 3] = -3.0
    ds = Dataset(
        images=rng.integers(0, 256, (4, H, W, 1), dtype=np.uint8),
        kind="posed",
        poses=poses,
        source_index=np.array([0, 5, 0, 7]),
        drone=np.array([0, 0, 1, 1], np.int16),
        drone_names=["a.mp4", "b.mp4"],
        aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
    )
    cams = [
        Camera(5.0, 5.0, 3.0, 2.0, W, H),
        Camera(5.2, 5.1, 3.1, 2.0, W, H, "SIMPLE_RADIAL", (0.02,)),
    ]
    ds.set_cameras(cams, np.array([0, 0, 1, 1]))
    return ds


def test_cameras_and_drones_round_trip_and_subset(tmp_path: Path) -> None:
    ds = two_drones()
    assert ds.intrinsics is None
    back = open_dataset(write_dataset(tmp_path / "d.h5", ds))
    assert back.same_as(ds)
    assert back.camera_index.dtype == np.int16 and back.drone.dtype == np.int16
    assert back.camera_of(3) == ds.cameras[1] and back.camera_of(0) == ds.cameras[0]
    assert [k.fx for k in back.frame_cameras()] == [5.0, 5.0, 5.2, 5.2]
    assert back.drone_name(1) == "b.mp4"
    sub = back.subset(np.array([3, 0]))
    assert sub.drones().tolist() == [1, 0] and sub.camera_of(0) == ds.cameras[1]
    assert sub.cameras == ds.cameras


def test_one_camera_table_sets_intrinsics(tmp_path: Path) -> None:
    ds = two_drones()
    ds.set_cameras(ds.cameras[:1], np.zeros(4))
    assert ds.intrinsics == ds.cameras[0]
    back = open_dataset(write_dataset(tmp_path / "d.h5", ds))
    assert back.intrinsics == ds.cameras[0] and back.camera_of(2) == ds.cameras[0]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"camera_index": np.array([0, 0, 2, 1], np.int16)}, "camera_index: 2 is not a camera"),
        ({"camera_index": np.array([0, -1, 1, 1], np.int16)}, "camera_index: -1 is not a camera"),
        ({"camera_index": None}, "camera_index: missing"),
        ({"intrinsics": Camera(5.0, 5.0, 3.0, 2.0, W, H)}, "intrinsics: must be None"),
        ({"drone": np.array([0, 0, 1, 2], np.int16)}, "drone: drone 2 has no name"),
        ({"drone": np.array([0, 0, -1, 1], np.int16)}, "drone: numbers must be >= 0"),
        ({"drone": np.array([0, 1], np.int16)}, "drone: has shape [2], expected [4]"),
        ({"cameras": [Camera(5.0, 5.0, 3.0, 2.0, 8, H)] * 2}, "cameras[0]: are for 8x4"),
        ({"cameras": [Camera(-5.0, 5.0, 3.0, 2.0, W, H)] * 2}, "cameras[0]: focal lengths"),
    ],
)
def test_bad_camera_tables_are_refused_before_writing(
    tmp_path: Path, change: dict, message: str
) -> None:
    ds = dataclasses.replace(two_drones(), **change)
    with pytest.raises(DatasetError, match=message.replace("[", r"\[").replace("]", r"\]")):
        write_dataset(tmp_path / "bad.h5", ds)
    assert not (tmp_path / "bad.h5").exists()


def test_damaged_camera_table_on_disk_is_one_line(tmp_path: Path) -> None:
    p = write_dataset(tmp_path / "d.h5", two_drones())
    with h5py.File(p, "r+") as f:
        f.attrs["cameras"] = np.bytes_(b'[{"fx": 1}]')
    with pytest.raises(DatasetError, match=r"cameras\[0\]: must be a JSON object") as err:
        open_dataset(p)
    assert len(str(err.value).splitlines()) == 1 and str(p) in str(err.value)


def test_version_2_file_reads_as_one_camera_and_drone_0(tmp_path: Path) -> None:
    """A file as version 2 wrote it: checksums, `intrinsics` only, no camera table."""
    ds = two_drones()
    single = dataclasses.replace(ds, cameras=None, camera_index=None, drone=None, drone_names=None)
    single.intrinsics = ds.cameras[0]
    p = write_dataset(tmp_path / "v2.h5", single)
    with h5py.File(p, "r+") as f:
        f.attrs["format_version"] = np.int64(2)
    back = open_dataset(p)
    assert back.cameras is None and back.camera_of(3) == ds.cameras[0]
    assert back.drones().tolist() == [0, 0, 0, 0] and back.drone_name(0) == "drone_0"
