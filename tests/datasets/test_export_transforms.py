"""Export to transforms.json + PNGs + PLY + COLMAP: pose convention round trip, images, cameras,
the nerfstudio / instant-ngp loaders' rules key by key, the COLMAP model in the exported frame."""

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
from dronecap.datasets.trajectory import read_tum
from dronecap.errors import InputError

from .interop import lego_colmap_model, nerfstudio_rules, ngp_lens, ngp_rules, reprojection_px


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
    out = export_transforms(write_dataset(tmp_path / "d.h5", ds), tmp_path / "x").out_dir
    meta = json.loads((out / "transforms.json").read_text())
    gl = np.array([f["transform_matrix"] for f in meta["frames"]])
    # OpenGL camera: same centre and x axis, y and z flipped
    np.testing.assert_array_equal(gl[:, :3, 3], ds.poses[:, :3, 3])
    np.testing.assert_array_equal(gl[:, :3, 0], ds.poses[:, :3, 0])
    np.testing.assert_array_equal(gl[:, :3, 1:3], -ds.poses[:, :3, 1:3])
    np.testing.assert_allclose(opengl_to_opencv(gl), ds.poses, atol=1e-15)
    t, tum = read_tum(out / "trajectory_tum.txt")  # the same poses as a TUM trajectory
    np.testing.assert_allclose(tum, ds.poses, atol=1e-8)
    np.testing.assert_array_equal(t, np.arange(ds.n))
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
    # no val split: nerfstudio needs all three lists once one is there; val is the test split
    assert (
        meta["val_filenames"] == meta["test_filenames"] == ["images/00003.png", "images/00004.png"]
    )
    assert [f["dronecap_name"] for f in meta["frames"]] == ds.names
    # cx = 4.5 != w / 2: not a Blender camera, so the per-split files carry no camera_angle_x
    # (import-blender cannot misread them); instant-ngp reads fl_x first anyway
    assert "camera_angle_x" not in json.loads((out / "transforms_train.json").read_text())


@pytest.mark.parametrize(("channels", "alpha"), [(3, True), (1, True), (3, False), (1, False)])
def test_images_round_trip(tmp_path: Path, channels: int, alpha: bool) -> None:
    ds = small_dataset(channels, alpha)
    out = export_transforms(write_dataset(tmp_path / "d.h5", ds), tmp_path / "x").out_dir
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


@pytest.mark.parametrize(
    ("model", "dist", "ns_model", "ns_keys", "ngp"),
    [
        ("SIMPLE_RADIAL", (0.05,), "OPENCV", {"k1": 0.05, "k2": 0, "p1": 0, "p2": 0},
         ("OpenCV", [0.05, 0, 0, 0])),
        ("OPENCV", (0.05, -0.01, 0.002, -0.003), "OPENCV",
         {"k1": 0.05, "k2": -0.01, "p1": 0.002, "p2": -0.003},
         ("OpenCV", [0.05, -0.01, 0.002, -0.003])),
        ("OPENCV_FISHEYE", (0.1, -0.02, 0.003, -0.004), "OPENCV_FISHEYE",
         {"k1": 0.1, "k2": -0.02, "k3": 0.003, "k4": -0.004},
         ("OpenCVFisheye", [0.1, -0.02, 0.003, -0.004])),
        ("FULL_OPENCV", (0.05, -0.01, 0.002, -0.003, 0, 0, 0, 0), "OPENCV",
         {"k1": 0.05, "k2": -0.01, "p1": 0.002, "p2": -0.003},
         ("OpenCV", [0.05, -0.01, 0.002, -0.003])),
    ],
)  # fmt: skip
def test_every_camera_model_as_both_tools_read_it(
    tmp_path: Path, model: str, dist: tuple, ns_model: str, ns_keys: dict, ngp: tuple
) -> None:
    k = Intrinsics(10.0, 11.0, 4.2, 3.1, 8, 6, model, dist)
    out = export_transforms(
        write_dataset(tmp_path / "d.h5", small_dataset(3, False, k)), tmp_path / "x"
    ).out_dir
    meta = json.loads((out / "transforms.json").read_text())
    # nerfstudio: the model name and exactly the distortion keys its parser reads
    assert meta["camera_model"] == ns_model
    assert {key: meta[key] for key in ("k1", "k2", "k3", "k4", "p1", "p2") if key in meta} == (
        pytest.approx(ns_keys)
    )
    assert nerfstudio_rules(out) == []
    # instant-ngp: per-split files for every model, its four lens slots hold the same lens
    for split, test_frames in (("train", {"images/00003.png", "images/00004.png"}),
                               ("test", {"images/00000.png"})):  # fmt: skip
        path = out / f"transforms_{split}.json"
        assert ngp_rules(path, must_not_contain=test_frames) == []
        mode, params = ngp_lens(json.loads(path.read_text()))
        assert mode == ngp[0]
        np.testing.assert_allclose(params, ngp[1])
    assert (
        not (out / "transforms_val.json").exists() or ngp_rules(out / "transforms_val.json") == []
    )


def test_k3_goes_to_nerfstudio_only_and_rational_terms_are_refused(tmp_path: Path) -> None:
    k = Intrinsics(10.0, 10.0, 4.0, 3.0, 8, 6, "FULL_OPENCV", (0.05, 0, 0, 0, 0.01, 0, 0, 0))
    res = export_transforms(
        write_dataset(tmp_path / "d.h5", small_dataset(3, False, k)), tmp_path / "x"
    )
    meta = json.loads((res.out_dir / "transforms.json").read_text())
    assert meta["k3"] == 0.01 and nerfstudio_rules(res.out_dir) == []
    # instant-ngp's slot 2 is shared by k3 and p1: no per-split file rather than a wrong lens
    assert res.split_files == [] and any("k3" in n for n in res.notes)
    assert not list(res.out_dir.glob("transforms_*.json"))
    rational = Intrinsics(10.0, 10.0, 4.0, 3.0, 8, 6, "FULL_OPENCV", (0.05, 0, 0, 0, 0, 0.2, 0, 0))
    src = write_dataset(tmp_path / "r.h5", small_dataset(3, False, rational))
    with pytest.raises(InputError, match="rational"):
        export_transforms(src, tmp_path / "y")
    assert not (tmp_path / "y").exists()


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


def test_lego_export_passes_the_loaders_rules(lego_h5: Path, tmp_path: Path) -> None:
    out = export_transforms(lego_h5, tmp_path / "x").out_dir
    meta = json.loads((out / "transforms.json").read_text())
    assert nerfstudio_rules(out) == []
    ds = open_dataset(lego_h5)
    counts = {s: len(meta[f"{s}_filenames"]) for s in ("train", "val", "test")}
    assert counts == {s: len(ds.indices(s)) for s in ("train", "val", "test")}  # a real val split
    np.testing.assert_array_equal(meta["applied_transform"], np.eye(4)[:3])
    np.testing.assert_array_equal(meta["aabb"], ds.aabb)
    assert meta["aabb_scale"] == 1 and "ply_file_path" not in meta  # no sparse points
    test = set(meta["test_filenames"]) | set(meta["val_filenames"])
    assert ngp_rules(out / "transforms_train.json", must_not_contain=test) == []
    train = json.loads((out / "transforms_train.json").read_text())["frames"]
    assert [f["file_path"] for f in train] == meta["train_filenames"]


def test_lego_export_imports_back_unchanged(lego_h5: Path, tmp_path: Path) -> None:
    out = export_transforms(lego_h5, tmp_path / "x").out_dir
    back = open_dataset(import_blender(out, tmp_path / "back.h5", resolution=160, progress=False))
    ds = open_dataset(lego_h5)
    for name in ("images", "alpha", "split"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name), err_msg=name)
    np.testing.assert_allclose(back.poses, ds.poses, atol=1e-12)
    assert back.intrinsics.fx == pytest.approx(ds.intrinsics.fx, rel=1e-12)
    np.testing.assert_allclose(back.aabb, ds.aabb)


def test_colmap_model_and_coloured_cloud_in_the_exported_frame(
    lego_h5: Path, tmp_path: Path
) -> None:
    """A COLMAP model in its own frame -> import-colmap (normalised) -> export with the model:
    the PLY, the COLMAP model and transforms.json agree in the exported frame."""
    import pycolmap

    from dronecap.datasets.import_colmap import import_colmap

    o3d = pytest.importorskip("open3d", reason="the [sim] extra reads the PLY")

    lego = open_dataset(lego_h5)
    s, _ = lego_colmap_model(lego, tmp_path / "m")
    src = import_colmap(tmp_path / "m/sparse", tmp_path / "m/images", tmp_path / "d.h5",
                        progress=False)  # fmt: skip
    ds = open_dataset(src)
    res = export_transforms(src, tmp_path / "x", tmp_path / "m/sparse")
    out = res.out_dir
    meta = json.loads((out / "transforms.json").read_text())
    assert nerfstudio_rules(out) == [] and res.points > 0
    np.testing.assert_allclose(meta["applied_transform"], ds.normalization[:3], atol=1e-12)
    model = pycolmap.Reconstruction(str(tmp_path / "m/sparse"))
    # the cloud: every model point seen twice, moved by the normalisation, colours kept
    pcd = o3d.io.read_point_cloud(str(out / meta["ply_file_path"]))
    xyz = np.array([p.xyz for p in model.points3D.values()])
    rgb = np.array([p.color for p in model.points3D.values()])
    want = xyz @ ds.normalization[:3, :3].T + ds.normalization[:3, 3]
    order = np.lexsort(want.T)
    got = np.asarray(pcd.points)
    got_order = np.lexsort(got.T)
    np.testing.assert_allclose(got[got_order], want[order], atol=1e-5)
    np.testing.assert_array_equal(np.round(np.asarray(pcd.colors)[got_order] * 255), rgb[order])
    # the COLMAP model (binary and text): observations reproject through transforms.json
    fx, fy, cx, cy = (meta[key] for key in ("fl_x", "fl_y", "cx", "cy"))
    c2w = {
        f["file_path"]: opengl_to_opencv(np.array(f["transform_matrix"])) for f in meta["frames"]
    }
    for sub in ("colmap/sparse/0", "colmap/text"):
        rec = pycolmap.Reconstruction(str(out / sub))
        assert rec.num_reg_images() == ds.n and rec.num_points3D() == res.points
        errs = []
        for image in rec.images.values():
            pose = c2w[f"images/{image.name}"]
            for p2 in image.points2D:
                pc = (rec.points3D[p2.point3D_id].xyz - pose[:3, 3]) @ pose[:3, :3]
                uv = [fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy]
                errs.append(np.hypot(*(uv - p2.xy)))
        assert len(errs) == res.observations and max(errs) < 1e-3


def test_a_model_that_is_not_the_datasets_is_refused(lego_h5: Path, tmp_path: Path) -> None:
    lego_colmap_model(open_dataset(lego_h5), tmp_path / "m")
    with pytest.raises(InputError, match="not the model this dataset came from"):
        export_transforms(lego_h5, tmp_path / "x", tmp_path / "m/sparse")
    assert not (tmp_path / "x").exists()


def test_cli_default_paths(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_dataset(tmp_path / "dataset.h5", small_dataset(1, False))
    (tmp_path / "sfm" / "model").mkdir(parents=True)  # a stale/foreign model is not used
    assert main(["export-transforms", "--workdir", str(tmp_path)]) == 0
    assert "5 frames" in capsys.readouterr().out
    assert (tmp_path / "transforms" / "images" / "00004.png").exists()


@pytest.mark.slow
def test_captured_flight_export_loads_in_both_tools(tmp_path: Path) -> None:
    """simulate -> ingest -> sfm -> split -> export: the anchors' rules on a real SfM output,
    with the SfM model's coloured points and observations in the exported frame."""
    import pycolmap

    w = ["--workdir", str(tmp_path)]
    steps = [
        ["simulate", "--frames", "120", "--seed", "2"],
        ["ingest", str(tmp_path / "flight.mp4")],
        ["sfm", "--gt", str(tmp_path / "flight.json")],
        ["split"],
        ["export-transforms"],
    ]
    for cmd in steps:
        assert main(["-q", *cmd, *w]) == 0, cmd
    out = tmp_path / "transforms"
    meta = json.loads((out / "transforms.json").read_text())
    assert nerfstudio_rules(out) == [] and "ply_file_path" in meta
    test = set(meta["test_filenames"])
    assert meta["val_filenames"] == meta["test_filenames"] and test
    assert ngp_rules(out / "transforms_train.json", must_not_contain=test) == []
    ds = open_dataset(tmp_path / "dataset.h5")
    np.testing.assert_allclose(meta["applied_transform"], ds.normalization[:3])
    rec = pycolmap.Reconstruction(str(out / "colmap/sparse/0"))
    assert rec.num_reg_images() == ds.n and rec.num_points3D() > 100
    # every observation reprojects through transforms.json's camera and poses (SfM residuals)
    assert np.median(reprojection_px(rec, meta, ds.intrinsics)) < 1.0
