"""The HDF5 dataset format: round trip of every field, refusal of bad files, atomic writes."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from dronecap.datasets.format import (
    FORMAT_VERSION,
    Dataset,
    DatasetError,
    Intrinsics,
    open_dataset,
    provenance,
    read_header,
    write_dataset,
)


def full_dataset(channels: int = 3) -> Dataset:
    """Three 4x5 frames with every optional field filled."""
    rng = np.random.default_rng(0)
    n, h, w = 3, 4, 5
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    return Dataset(
        images=rng.integers(0, 256, (n, h, w, channels), dtype=np.uint8),
        kind="posed",
        alpha=rng.integers(0, 256, (n, h, w), dtype=np.uint8),
        poses=poses,
        intrinsics=Intrinsics(5.5, 6.5, 2.5, 2.0, w, h, "SIMPLE_RADIAL", (0.01,)),
        names=["a.png", "b.png", "ü.png"],
        source_index=np.array([3, 7, 11]),
        timestamps=np.array([0.1, 0.2, 0.35]),
        split=np.array([0, 2, -1]),
        near_far=np.array([[0.1, 2.0], [0.2, 3.0], [0.3, 4.0]]),
        aabb=np.array([[-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]]),
        normalization=np.diag([2.0, 2.0, 2.0, 1.0]),
        background=(1.0,) * channels,
        shards={"iid": np.array([0, -1, 1]), "sector": np.array([1, -1, 0])},
        extra={"sharpness": np.array([1.5, 2.5, 3.5]), "label": np.array(["x", "y", "z"])},
        provenance=provenance("test", {"k": 1}, {"in.h5": "ab" * 32}),
        attrs={"scene": "unit", "list": [1, 2]},
    )


@pytest.mark.parametrize("channels", [1, 3])
def test_every_field_round_trips(tmp_path: Path, channels: int) -> None:
    ds = full_dataset(channels)
    back = open_dataset(write_dataset(tmp_path / "d.h5", ds))
    assert back.kind == "posed" and back.n == 3 and back.channels == channels
    for name in ("images", "alpha", "poses", "source_index", "timestamps", "split", "near_far"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name), err_msg=name)
    assert back.images.dtype == np.uint8 and back.poses.dtype == np.float64
    assert back.split.dtype == np.int8
    assert back.intrinsics == ds.intrinsics
    assert back.names == ds.names
    np.testing.assert_array_equal(back.aabb, ds.aabb)
    np.testing.assert_array_equal(back.normalization, ds.normalization)
    assert back.background == ds.background
    assert set(back.shards) == {"iid", "sector"}
    for k, v in ds.shards.items():
        np.testing.assert_array_equal(back.shards[k], v)
        assert back.shards[k].dtype == np.int16
    np.testing.assert_array_equal(back.extra["sharpness"], ds.extra["sharpness"])
    assert back.extra["label"].tolist() == ["x", "y", "z"]
    assert back.provenance == ds.provenance
    assert back.attrs == ds.attrs
    assert read_header(tmp_path / "d.h5")["format_version"] == FORMAT_VERSION


def test_images_are_chunked_per_frame_and_not_gzip(tmp_path: Path) -> None:
    write_dataset(tmp_path / "d.h5", full_dataset())
    with h5py.File(tmp_path / "d.h5") as f:
        assert f["images"].chunks == (1, 4, 5, 3)
        assert f["images"].compression in (None, "lzf")


def test_minimal_dataset_round_trips(tmp_path: Path) -> None:
    ds = Dataset(images=np.zeros((2, 3, 3, 1), np.uint8))
    back = open_dataset(write_dataset(tmp_path / "m.h5", ds))
    assert back.alpha is None and back.poses is None and back.intrinsics is None
    assert back.shards == {} and back.extra == {} and back.background is None


def assert_one_line_naming(err: pytest.ExceptionInfo, path: Path) -> None:
    msg = str(err.value)
    assert "\n" not in msg
    assert str(path) in msg


def assert_refused(p: Path, ds: Dataset, message: str) -> None:
    """Writing ``ds`` to ``p`` fails before anything is written, in one line naming ``p`` and
    saying ``message``."""
    with pytest.raises(DatasetError) as err:
        write_dataset(p, ds)
    assert_one_line_naming(err, p)
    assert message in str(err.value)
    assert not p.exists()


def make_bad_file(p: Path, case: str) -> None:
    """Write a file at ``p`` that is broken in the way ``case`` names."""
    if case == "missing":
        return
    if case == "corrupt":
        p.write_bytes(np.random.default_rng(1).bytes(4096))
        return
    if case == "foreign":
        with h5py.File(p, "w") as f:
            f["images"] = np.zeros((1, 2, 2, 3), np.uint8)
            f.attrs["format"] = "someone-else"
        return
    write_dataset(p, full_dataset())
    if case == "truncated":
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
        return
    with h5py.File(p, "a") as f:
        if case == "newer":
            f.attrs["format_version"] = FORMAT_VERSION + 1
        elif case == "no_images":
            del f["images"]


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", "no such file"),
        ("corrupt", "not a readable HDF5 file"),
        ("foreign", "someone-else"),
        ("truncated", "truncated"),
        ("newer", "newer"),
        ("no_images", "images"),
        ("wrong_kind", "expected one of ['dataset', 'shard']"),
    ],
)
def test_bad_files_fail_with_one_line(tmp_path: Path, case: str, message: str) -> None:
    p = tmp_path / f"{case}.h5"
    make_bad_file(p, case)
    with pytest.raises(DatasetError) as err:
        open_dataset(p, kinds=("dataset", "shard"))
    assert_one_line_naming(err, p)
    assert message in str(err.value)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("poses", np.tile(np.eye(4), (2, 1, 1)), "poses: has shape [2, 4, 4], expected [3, 4, 4]"),
        ("alpha", np.zeros((3, 4, 5), np.float32), "alpha: wrong type"),
        ("split", np.array([0, 2, 5]), "split: values must be -1, 0, 1 or 2, found [0, 2, 5]"),
        ("aabb", np.array([[0.0, 0, 0], [1, -1, 1]]), "max > min"),
        ("background", (1.0,), "background: has 1 values for 3 channels"),
    ],
)
def test_inconsistent_fields_are_refused_before_writing(
    tmp_path: Path, field: str, value: object, message: str
) -> None:
    ds = full_dataset()
    setattr(ds, field, value)
    assert_refused(tmp_path / "bad.h5", ds, message)


def test_failed_write_leaves_no_file_and_keeps_the_old_one(tmp_path: Path) -> None:
    p = write_dataset(tmp_path / "d.h5", full_dataset())
    before = p.read_bytes()
    ds = full_dataset()
    ds.extra["unstorable"] = np.array([{}, {}], dtype=object)  # h5py fails after images are written
    with pytest.raises(TypeError):
        write_dataset(p, ds)
    assert p.read_bytes() == before
    with pytest.raises(TypeError):
        write_dataset(tmp_path / "fresh.h5", ds)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["d.h5"]


def test_every_array_is_checksummed_and_a_flipped_image_byte_is_an_error(tmp_path: Path) -> None:
    ds = full_dataset()
    ds.images = np.full_like(ds.images, 77)  # constant images: lzf stores long runs
    p = write_dataset(tmp_path / "d.h5", ds)
    with h5py.File(p) as f:
        arrays = []
        f.visititems(lambda name, obj: arrays.append(obj) if isinstance(obj, h5py.Dataset) else 0)
        assert arrays and all(a.fletcher32 for a in arrays)
        offset = f["images"].id.get_chunk_info(1).byte_offset  # frame 1's stored bytes
    raw = bytearray(p.read_bytes())
    raw[offset + 2] ^= 0x01
    p.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match="images: checksum mismatch") as err:
        open_dataset(p)
    assert_one_line_naming(err, p)


def test_version_1_files_without_checksums_still_read(tmp_path: Path) -> None:
    """A file as version 1 wrote them: default HDF5 layout, no filters but lzf, str attrs."""
    p = tmp_path / "v1.h5"
    images = np.arange(2 * 3 * 4 * 1, dtype=np.uint8).reshape(2, 3, 4, 1)
    with h5py.File(p, "w") as f:
        f.attrs["format"] = "dronecap"
        f.attrs["format_version"] = 1
        f.attrs["kind"] = "posed"
        f.create_dataset("images", data=images, chunks=(1, 3, 4, 1), compression="lzf")
        f["poses"] = np.tile(np.eye(4), (2, 1, 1))
        f["names"] = np.array(["a", "b"], dtype=h5py.string_dtype())
        f.attrs["intrinsics"] = '{"fx": 3.0, "fy": 3.0, "cx": 2.0, "cy": 1.5, "width": 4, ' + (
            '"height": 3, "model": "PINHOLE", "distortion": []}'
        )
        f.attrs["provenance"] = "{}"
    ds = open_dataset(p)
    np.testing.assert_array_equal(ds.images, images)
    assert ds.names == ["a", "b"] and ds.intrinsics == Intrinsics(3.0, 3.0, 2.0, 1.5, 4, 3)
    assert read_header(p)["format_version"] == 1


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("poses", "reflect", "poses: frame 1: rotation is a reflection"),
        ("poses", "scale", "poses: frame 1: rotation is not orthonormal"),
        ("poses", "nan", "poses: contains non-finite values"),
        ("near_far", np.array([[0.1, 2.0], [3.0, 2.0], [0.3, 4.0]]), "near_far: must satisfy"),
        ("aabb", np.array([[0.0, 0, np.inf], [1, 1, 1]]), "aabb: must be finite"),
        ("aabb", np.array([[50.0, 50, 50], [51, 51, 51]]), "outside every camera's view"),
        ("background", (1.0, float("nan"), 0.0), "background: values must be finite"),
        ("background", (1.0, 1.5, 0.0), "background: values must be finite and in [0, 1]"),
        ("intrinsics", Intrinsics(float("inf"), 6.5, 2.5, 2.0, 5, 4), "intrinsics: non-finite"),
        ("timestamps", np.array([0.0, np.nan, 1.0]), "timestamps: contains non-finite"),
    ],
)
def test_geometry_is_validated_on_write(tmp_path: Path, field: str, value, message: str) -> None:
    ds = full_dataset()
    ds.poses[:, :3, 3] = [[0, 0, -3], [0.5, 0, -3], [-0.5, 0, -3]]  # in front of the box
    if isinstance(value, str) and value == "reflect":
        ds.poses[1, :3, 0] *= -1
    elif isinstance(value, str) and value == "scale":
        ds.poses[1, :3, :3] *= 1.05
    elif isinstance(value, str) and value == "nan":
        ds.poses[2, 0, 3] = np.nan
    else:
        setattr(ds, field, value)
    assert_refused(tmp_path / "bad.h5", ds, message)
