"""`dronecap import-transforms`: exports come back unchanged, a distorted nerfstudio dataset
imports (camera scaled exactly, distortion kept) and trains, instant-ngp layouts, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.cli import main
from dronecap.datasets.blender import opengl_to_opencv
from dronecap.datasets.export import export_transforms
from dronecap.datasets.format import open_dataset
from dronecap.datasets.import_colmap import import_colmap
from dronecap.datasets.import_transforms import import_transforms
from dronecap.errors import InputError

from .interop import lego_colmap_model

FACES = np.array([[230, 30, 30], [30, 200, 50], [30, 50, 230], [230, 200, 30], [30, 200, 200],
                  [200, 50, 200]], np.uint8)  # fmt: skip


def render_cube(c2w: np.ndarray, k: Camera) -> np.ndarray:
    """uint8 RGB [H, W, 3] of the face-coloured cube [-0.5, 0.5]^3 on white, through ``k``'s
    lens (rays from OpenCV's undistortion of every pixel centre)."""
    d = k.pixel_directions().astype(float) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (-0.5 - o) / d, (0.5 - o) / d
    tn, tf = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    hit = (tf > tn) & (tf > 0)
    axis = np.argmax(np.minimum(t0, t1), -1)
    p = o + d * tn[..., None]
    face = axis * 2 + (np.take_along_axis(p, axis[..., None], -1)[..., 0] > 0)
    return np.where(hit[..., None], FACES[face], 255).astype(np.uint8)


def look_at_gl(eye: np.ndarray) -> np.ndarray:
    """Camera-to-world, OpenGL axes, looking at the origin, world up +z."""
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(right, fwd), -fwd, eye
    return m


DISTORTED = Camera(70.0, 72.0, 33.0, 31.0, 64, 64, "OPENCV", (-0.12, 0.03, 0.002, -0.001))


def write_nerfstudio_scene(root: Path, k: Camera = DISTORTED, n: int = 16) -> Path:
    """A nerfstudio dataset of the cube: per-frame intrinsics (all equal), OPENCV distortion,
    no split lists, no scene box (bounds come from the cameras)."""
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(n):
        th = 2 * np.pi * i / n
        gl = look_at_gl(np.array([2.6 * np.cos(th), 2.6 * np.sin(th), 1.0 + 0.3 * np.sin(3 * th)]))
        bgr = render_cube(opengl_to_opencv(gl), k)[:, :, ::-1]
        cv2.imwrite(str(root / f"images/frame_{i:03d}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, 98])
        frames.append({"file_path": f"images/frame_{i:03d}.jpg", "transform_matrix": gl.tolist(),
                       "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width,
                       "h": k.height, "k1": k.distortion[0], "k2": k.distortion[1],
                       "p1": k.distortion[2], "p2": k.distortion[3]})  # fmt: skip
    (root / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    return root


def test_lego_export_imports_back_exactly(lego_h5: Path, tmp_path: Path) -> None:
    out = export_transforms(lego_h5, tmp_path / "x").out_dir
    back = open_dataset(import_transforms(out, tmp_path / "back.h5", progress=False))
    ds = open_dataset(lego_h5)
    for name in ("images", "alpha", "split", "aabb", "normalization"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name), err_msg=name)
    np.testing.assert_allclose(back.poses, ds.poses, atol=1e-6)
    assert back.intrinsics == ds.intrinsics and back.names == ds.names


def test_normalised_flight_with_points_imports_back(lego_h5: Path, tmp_path: Path) -> None:
    """A dataset that went through SfM-style normalisation (import-colmap) exports with its PLY
    and comes back with the same poses, images, AABB, normalisation and points."""
    lego_colmap_model(open_dataset(lego_h5), tmp_path / "m")
    src = import_colmap(tmp_path / "m/sparse", tmp_path / "m/images", tmp_path / "d.h5",
                        size=96, progress=False)  # fmt: skip
    out = export_transforms(src, tmp_path / "x", tmp_path / "m/sparse").out_dir
    back = open_dataset(import_transforms(out / "transforms.json", tmp_path / "b.h5",
                                          size=96, progress=False))  # fmt: skip
    ds = open_dataset(src)
    np.testing.assert_allclose(back.poses, ds.poses, atol=1e-6)
    for name in ("images", "split", "aabb"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name), err_msg=name)
    np.testing.assert_allclose(back.normalization, ds.normalization, atol=1e-12)
    assert back.intrinsics == ds.intrinsics and back.alpha is None
    assert len(back.extra["points3d_xyz"]) > 0


def test_distorted_nerfstudio_dataset_imports_scaled_and_trains(tmp_path: Path) -> None:
    scene = write_nerfstudio_scene(tmp_path / "scene")
    out = tmp_path / "work"
    assert main(["import-transforms", str(scene), "--size", "48", "--workdir", str(out)]) == 0
    ds = open_dataset(out / "dataset.h5")
    k = ds.intrinsics
    # 64 -> 48 px: every focal length and principal point times 0.75, distortion unchanged
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (52.5, 54.0, 24.75, 23.25, 48, 48)
    assert k.model == "OPENCV" and k.distortion == DISTORTED.distortion
    assert ds.channels == 3 and ds.alpha is None and ds.hw == (48, 48)
    assert len(ds.indices("test")) == 2 and len(ds.indices("train")) == 14  # every 8th to test
    # bounds as for a flight: normalised into [-1, 1]^3 around the cameras, up = +z
    assert np.abs(ds.aabb).max() <= 1.2 and (ds.near_far[:, 0] < ds.near_far[:, 1]).all()
    np.testing.assert_allclose(ds.normalization[:3, :3] @ [0, 0, 1] / np.cbrt(
        np.linalg.det(ds.normalization[:3, :3])), [0, 0, 1], atol=0.05)  # fmt: skip
    run = out / "run"
    args = ["train", str(out / "dataset.h5"), "--preset", "test", "--steps", "20", "--out",
            str(run), "--no-progress", "--threads", "1"]  # fmt: skip
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["steps"] == 20 and np.isfinite(metrics["test"]["psnr"])


def test_instant_ngp_layout_with_split_files(tmp_path: Path) -> None:
    """transforms_{train,test}.json, camera_angle_x only, file paths without extension, gray."""
    root = tmp_path / "ngp"
    root.mkdir()
    k = Camera(40.0, 40.0, 20.0, 20.0, 40, 40)
    angle = 2 * np.arctan(20 / 40)
    for split, idx in (("train", range(6)), ("test", range(6, 8))):
        frames = []
        for i in idx:
            gl = look_at_gl(np.array([2.5 * np.cos(i), 2.5 * np.sin(i), 0.8]))
            gray = render_cube(opengl_to_opencv(gl), k) @ np.array([0.299, 0.587, 0.114])
            cv2.imwrite(str(root / f"r_{i}.png"), np.round(gray).astype(np.uint8))
            frames.append({"file_path": f"./r_{i}", "transform_matrix": gl.tolist()})
        data = {"camera_angle_x": angle, "aabb_scale": 4, "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(data))
    ds = open_dataset(import_transforms(root, tmp_path / "d.h5", size=40, progress=False))
    assert ds.channels == 1 and ds.n == 8
    assert ds.split.tolist() == [0] * 6 + [2] * 2
    assert ds.intrinsics.fx == pytest.approx(40.0, rel=1e-12) and ds.intrinsics.cx == 20.0
    want = cv2.imread(str(root / "r_7.png"), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(ds.images[7, :, :, 0], want)


def _scene_with(tmp_path: Path, change) -> Path:
    root = write_nerfstudio_scene(tmp_path / "s", n=4)
    meta = json.loads((root / "transforms.json").read_text())
    change(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m.update(camera_model="EQUIRECTANGULAR"), "camera_model 'EQUIRECTANGULAR'"),
        (lambda m: m["frames"][0].update(k4=0.01), "k4"),
        (lambda m: m["frames"][2].update(transform_matrix=[[1, 0], [0, 1]]),
         "frame 2: transform_matrix"),
        (lambda m: m["frames"][3].update(file_path="images/missing.png"), "missing"),
        (lambda m: m.update(train_filenames=["images/nope.png"]), "which no frame has"),
        (lambda m: m.update(train_filenames=["images/frame_000.jpg"],
                            test_filenames=["images/frame_000.jpg"]), "both train"),
        (lambda m: [(f.pop("fl_x"), f.pop("fl_y")) for f in m["frames"]], "no focal length"),
        (lambda m: m["frames"][0].update(w=128), "camera is for 128x64"),
        (lambda m: m.update(aabb=[[0, 0, 0], [0, 1, 1]]), "aabb must be"),
    ],
)  # fmt: skip
def test_bad_datasets_are_refused_with_one_line(tmp_path: Path, change, message: str) -> None:
    root = _scene_with(tmp_path, change)
    with pytest.raises(InputError, match=message) as err:
        import_transforms(root, tmp_path / "d.h5", progress=False)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "d.h5").exists()


def test_per_frame_intrinsics_give_a_camera_per_frame(tmp_path: Path) -> None:
    root = _scene_with(tmp_path, lambda m: m["frames"][1].update(fl_x=60.0, fl_y=60.0))
    ds = open_dataset(import_transforms(root, tmp_path / "d.h5", progress=False))
    assert len(ds.cameras) == 2 and ds.intrinsics is None
    assert ds.camera_index.tolist() == [0, 1, 0, 0]
    meta = json.loads((root / "transforms.json").read_text())
    base = meta["frames"][0].get("fl_x", meta.get("fl_x"))
    assert ds.camera_of(1).fx / ds.camera_of(0).fx == pytest.approx(60.0 / base)
    out = tmp_path / "out"
    assert main(["export-transforms", str(tmp_path / "d.h5"), "-o", str(out)]) == 0
    meta = json.loads((out / "transforms.json").read_text())
    fx = [f["fl_x"] for f in meta["frames"]]
    assert fx[1] == ds.camera_of(1).fx and fx[0] == fx[2] == ds.camera_of(0).fx
    back = open_dataset(import_transforms(out, tmp_path / "back.h5", progress=False))
    assert back.cameras == ds.cameras and back.camera_index.tolist() == [0, 1, 0, 0]


def test_cli_refusals(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["import-transforms", str(tmp_path / "none"), "--workdir", str(tmp_path)]) == 1
    assert "no such file or folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["import-transforms", str(tmp_path / "empty"), "--workdir", str(tmp_path)]) == 1
    assert "no transforms.json" in capsys.readouterr().err
    assert main(["import-transforms", str(tmp_path), "--size", "2"]) == 1
    assert "--size" in capsys.readouterr().err
    assert not (tmp_path / "dataset.h5").exists()


def test_object_capture_without_a_scene_box_is_carved(lego_h5: Path, tmp_path: Path) -> None:
    """A foreign nerfstudio object capture (no ``aabb``, RGBA, pinhole): normalised like a
    flight, then its AABB carved from the train masks as import-blender does."""
    out = export_transforms(lego_h5, tmp_path / "x").out_dir
    meta = json.loads((out / "transforms.json").read_text())
    for key in ("aabb", "aabb_scale", "applied_transform"):
        meta.pop(key)
    (out / "transforms.json").write_text(json.dumps(meta))
    ds = open_dataset(import_transforms(out, tmp_path / "d.h5", progress=False))
    lego = open_dataset(lego_h5)
    assert ds.attrs["bounds_from"] == "alpha carving"
    # inside the box of import-blender's AABB moved into the new frame (normalisation rotates
    # it about the vertical, so that box is looser), and far smaller than the cameras' box
    corners = np.stack(np.meshgrid(*lego.aabb.T, indexing="ij"), -1).reshape(8, 3)
    moved = corners @ ds.normalization[:3, :3].T + ds.normalization[:3, 3]
    pad = 0.05 * (moved.max(0) - moved.min(0))
    assert (ds.aabb[0] >= moved.min(0) - pad).all() and (ds.aabb[1] <= moved.max(0) + pad).all()
    assert np.prod(ds.aabb[1] - ds.aabb[0]) < 0.2 * np.prod(np.ptp(ds.poses[:, :3, 3], axis=0))
    c = ds.poses[:, :3, 3]
    assert not ((c > ds.aabb[0]) & (c < ds.aabb[1])).all(1).any()  # every camera outside
