"""Imports bound what the views see: instant-ngp's ``aabb_scale`` box, where the view axes
converge for an object captured from one side, the frusta of a forward capture — never the
camera centres alone."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.blender import opengl_to_opencv
from dronecap.datasets.bounds import FORWARD_DEPTH, lookat_point, view_centres
from dronecap.datasets.format import open_dataset
from dronecap.datasets.import_transforms import import_transforms, ngp_box

from .test_import_transforms import DISTORTED, look_at_gl, render_cube

CUBE = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])  # render_cube's object


def one_sided_capture(root: Path, aabb_scale: float | None, n: int = 14) -> Path:
    """The cube seen from a 70-degree arc at distance 3.2, through an OpenCV lens, written as
    colmap2nerf writes a capture (look-at point at the origin, no points); the camera centres'
    box lies to one side and does not hold the cube."""
    (root / "images").mkdir(parents=True)
    k = DISTORTED
    frames = []
    for i in range(n):
        th = np.radians(-35 + 70 * i / (n - 1))
        z = 0.8 + 0.6 * (i % 3)
        gl = look_at_gl(np.array([3.2 * np.cos(th), 3.2 * np.sin(th), z]))
        bgr = render_cube(opengl_to_opencv(gl), k)[:, :, ::-1]
        cv2.imwrite(str(root / f"images/{i:03d}.png"), bgr)
        frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": gl.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
            "w": k.width, "h": k.height, "k1": k.distortion[0], "k2": k.distortion[1],
            "p1": k.distortion[2], "p2": k.distortion[3], "frames": frames}  # fmt: skip
    if aabb_scale is not None:
        meta["aabb_scale"] = aabb_scale
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def _in_box(p: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    return ((p >= aabb[0]) & (p <= aabb[1])).all(-1)


def _cube_in_scene(ds) -> np.ndarray:
    corners = np.stack(np.meshgrid(*CUBE.T, indexing="ij"), -1).reshape(8, 3)
    return corners @ ds.normalization[:3, :3].T + ds.normalization[:3, 3]


def test_ngp_box_follows_instant_ngps_scale_offset_and_axis_order() -> None:
    box, what = ngp_box({"aabb_scale": 4}, Path("t.json"))
    np.testing.assert_allclose(box, [[-4 / 0.66] * 3, [4 / 0.66] * 3])
    assert "aabb_scale 4" in what
    # ngp axes are the file's (y, z, x): an offset on ngp z moves the box along file x
    box, _ = ngp_box({"aabb_scale": 1, "scale": 0.5, "offset": [0.5, 0.5, 0.2]}, Path("t.json"))
    np.testing.assert_allclose((box[0] + box[1]) / 2, [0.6, 0.0, 0.0])
    np.testing.assert_allclose(box[1] - box[0], [2.0] * 3)
    assert ngp_box({}, Path("t.json")) is None


@pytest.mark.parametrize("aabb_scale", [4, None])
def test_one_sided_object_capture_bounds_hold_what_the_views_see(
    tmp_path: Path, aabb_scale: float | None
) -> None:
    src = one_sided_capture(tmp_path / "src", aabb_scale)
    ds = open_dataset(import_transforms(src, tmp_path / "d.h5", progress=False))
    assert "view axes converge" in ds.attrs["bounds_from"]
    if aabb_scale:
        assert "aabb_scale 4 box" in ds.attrs["bounds_from"]
        np.testing.assert_allclose(ds.normalization, np.eye(4))  # the file's frame is kept
    c = lookat_point(ds.poses)
    assert _in_box(c, ds.aabb)
    assert _in_box(view_centres(ds.poses, c), ds.aabb).all()
    assert _in_box(_cube_in_scene(ds), ds.aabb).all()
    # the camera centres' box (the old bounds) misses the object's centre
    centres = ds.poses[:, :3, 3]
    assert not _in_box(_cube_in_scene(ds).mean(0), np.stack([centres.min(0), centres.max(0)]))
    # and the box is about the object, not the whole capture
    assert np.ptp(ds.aabb, axis=0).max() < 2.0 * np.ptp(_cube_in_scene(ds), axis=0).max() * 1.8


def test_forward_capture_is_bounded_by_its_frusta(tmp_path: Path) -> None:
    """Cameras flying along x, all looking along +y (parallel axes that never converge)."""
    (tmp_path / "src" / "images").mkdir(parents=True)
    frames = []
    for i in range(10):
        gl = np.eye(4)
        gl[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # OpenGL: looks along world +y, up +z
        gl[:3, 3] = [0.2 * i, 0.0, 1.0]
        img = np.full((48, 64, 3), 40 + 10 * i, np.uint8)
        cv2.imwrite(str(tmp_path / f"src/images/{i}.png"), img)
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": gl.tolist()})
    meta = {"fl_x": 50.0, "w": 64, "h": 48, "frames": frames}
    (tmp_path / "src" / "transforms.json").write_text(json.dumps(meta))
    ds = open_dataset(import_transforms(tmp_path / "src", tmp_path / "d.h5", progress=False))
    assert "frusta" in ds.attrs["bounds_from"]
    o = ds.poses[:, :3, 3]
    assert _in_box(o, ds.aabb).all()
    extent = float(np.ptp(o, axis=0).max())
    ahead = o + 0.99 * FORWARD_DEPTH * extent * ds.poses[:, :3, 2]
    assert _in_box(ahead, ds.aabb).all()
    assert (ds.near_far[:, 1] > 0.9 * FORWARD_DEPTH * extent).all()


def test_cameras_that_neither_converge_nor_move_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    (tmp_path / "src" / "images").mkdir(parents=True)
    frames = []
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"src/images/{i}.png"), np.full((8, 8, 3), i * 50, np.uint8))
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": np.eye(4).tolist()})
    (tmp_path / "src" / "transforms.json").write_text(json.dumps({"fl_x": 8.0, "frames": frames}))
    assert (
        main(["-q", "import-transforms", str(tmp_path / "src"), "-o", str(tmp_path / "d.h5")]) == 1
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "neither converge" in err[0]
    assert not (tmp_path / "d.h5").exists()
