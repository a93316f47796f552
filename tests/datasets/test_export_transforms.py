"""Export to transforms.json + PNGs: pose convention round trip, images, cameras, errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.blender import import_blender, opengl_to_opencv
from dronecap.datasets.export import export_transforms
from dronecap.datasets.format import Dataset, Intrinsics, open_dataset, write_dataset
from dronecap.errors import InputError


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """float64 [n, 4, 4] camera-to-world with random rotations (QR of Gaussian matrices)."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = q, rng.normal(size=(n, 3))
    return poses


def small_dataset(channels: int, alpha: bool, k: Intrinsics | None = None) -> Dataset:
    rng = np.random.default_rng(1)
    n, h, w = 5, 6, 8
    return Dataset(
        images=rng.integers(0, 256, (n, h, w, channels), dtype=np.uint8),
        alpha=rng.integers(0, 256, (n, h, w), dtype=np.uint8) if alpha else None,
        poses=random_poses(n),
        intrinsics=k or Intrinsics(10.0, 10.0, 4.5, 3.0, w, h),
        split=np.array([0, 0, 0, 2, 2], np.int8),
        names=[f"f{i}" for i in range(n)],
        aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
    )


def test_pose_round_trip_opencv_opengl_opencv(tmp_path: Path) -> None:
    ds = small_dataset(3, alpha=True)
    out = export_transforms(write_dataset(tmp_path / "d.h5", ds), tmp_path / "x")
    meta = json.loads((out / "transforms.json").read_text())
    gl = np.array([f["transform_matrix"] for f in meta["frames"]])
    # OpenGL camera: same centre and x axis, y and z flipped
    np.testing.assert_array_equal(gl[:, :3, 3], ds.poses[:, :3, 3])
    np.testing.assert_array_equal(gl[:, :3, 0], ds.poses[:, :3, 0])
    np.testing.assert_array_equal(gl[:, :3, 1:3], -ds.poses[:, :3, 1:3])
    np.testing.assert_allclose(opengl_to_opencv(gl), ds.poses, atol=1e-15)
    k = ds.intrinsics
    assert [meta[key] for key in ("fl_x", "fl_y", "cx", "cy", "w", "h")] == [
        k.fx,
        k.fy,
        k.cx,
        k.cy,
        k.width,
        k.height,
    ]
    assert meta["camera_model"] == "PINHOLE"
    assert meta["train_filenames"] == ["images/00000.png", "images/00001.png", "images/00002.png"]
    assert "val_filenames" not in meta
    assert [f["dronecap_name"] for f in meta["frames"]] == ds.names
    # cx = 4.5 != w / 2: not a Blender camera, no Blender-layout files
    assert not (out / "transforms_train.json").exists()


@pytest.mark.parametrize(("channels", "alpha"), [(3, True), (1, True), (3, False), (1, False)])
def test_images_round_trip(tmp_path: Path, channels: int, alpha: bool) -> None:
    ds = small_dataset(channels, alpha)
    out = export_transforms(write_dataset(tmp_path / "d.h5", ds), tmp_path / "x")
    for i in range(ds.n):
        im = cv2.imread(str(out / f"images/{i:05d}.png"), cv2.IMREAD_UNCHANGED)
        if alpha:
            rgb = np.repeat(ds.images[i], 3, axis=2) if channels == 1 else ds.images[i]
            np.testing.assert_array_equal(im[:, :, 2::-1], rgb)
            np.testing.assert_array_equal(im[:, :, 3], ds.alpha[i])
        elif channels == 1:
            np.testing.assert_array_equal(im, ds.images[i, :, :, 0])
        else:
            np.testing.assert_array_equal(im[:, :, ::-1], ds.images[i])


def test_distortion_is_exported_as_opencv(tmp_path: Path) -> None:
    k = Intrinsics(10.0, 10.0, 4.0, 3.0, 8, 6, "SIMPLE_RADIAL", (0.05,))
    out = export_transforms(
        write_dataset(tmp_path / "d.h5", small_dataset(3, False, k)), tmp_path / "x"
    )
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV"
    assert (meta["k1"], meta["k2"], meta["p1"], meta["p2"]) == (0.05, 0.0, 0.0, 0.0)


def test_unknown_camera_model_is_refused_at_write(tmp_path: Path) -> None:
    k = Intrinsics(10.0, 10.0, 4.0, 3.0, 8, 6, "FISHEYE_WEIRD", (0.1, 0.2))
    with pytest.raises(InputError, match="unknown camera model"):
        write_dataset(tmp_path / "d.h5", small_dataset(3, False, k))
    assert not (tmp_path / "d.h5").exists()


@pytest.mark.parametrize("case", ["no_poses"])
def test_unexportable_inputs(tmp_path: Path, case: str) -> None:
    ds = small_dataset(3, False)
    ds.poses = None
    src = write_dataset(tmp_path / "d.h5", ds)
    with pytest.raises(InputError) as err:
        export_transforms(src, tmp_path / "x")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "x").exists()


def test_lego_export_imports_back_unchanged(lego_h5: Path, tmp_path: Path) -> None:
    out = export_transforms(lego_h5, tmp_path / "x")
    back = open_dataset(import_blender(out, tmp_path / "back.h5", resolution=160, progress=False))
    ds = open_dataset(lego_h5)
    for name in ("images", "alpha", "split"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name), err_msg=name)
    np.testing.assert_allclose(back.poses, ds.poses, atol=1e-12)
    assert back.intrinsics.fx == pytest.approx(ds.intrinsics.fx, rel=1e-12)
    np.testing.assert_allclose(back.aabb, ds.aabb)


def test_cli_default_paths(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_dataset(tmp_path / "dataset.h5", small_dataset(1, False))
    assert main(["export-transforms", "--workdir", str(tmp_path)]) == 0
    assert "5 frames" in capsys.readouterr().out
    assert (tmp_path / "transforms" / "images" / "00004.png").exists()
