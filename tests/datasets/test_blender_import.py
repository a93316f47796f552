"""NeRF Synthetic (Blender layout) import: pose convention, images, alpha, bounds, errors."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets.blender import import_blender, opengl_to_opencv
from dronecap.datasets.format import SPLITS, Dataset, open_dataset
from dronecap.errors import InputError


def test_known_blender_pose_maps_to_opencv() -> None:
    # Blender camera at (0, -4, 0) looking at the origin along +y, up = +z:
    # OpenGL axes: right (1,0,0), up (0,0,1), backwards (0,-1,0).
    gl = np.array([[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]], float)
    # OpenCV axes: right (1,0,0), down (0,0,-1), forward (0,1,0); same centre.
    cv = np.array([[1, 0, 0, 0], [0, 0, 1, -4], [0, -1, 0, 0], [0, 0, 0, 1]], float)
    np.testing.assert_array_equal(opengl_to_opencv(gl[None]), cv[None])
    np.testing.assert_array_equal(opengl_to_opencv(opengl_to_opencv(gl)), gl)


def ray_hits_box(o: np.ndarray, d: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Slab test: bool [M] for rays o [M,3] + t d [M,3], t > 0, against box [2,3]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (box[0] - o) / d, (box[1] - o) / d
    tmin = np.nanmax(np.minimum(t0, t1), -1)
    tmax = np.nanmin(np.maximum(t0, t1), -1)
    return (tmax >= tmin) & (tmax > 0)


def opaque_rays(ds: Dataset, views: np.ndarray, min_alpha: int) -> tuple[np.ndarray, np.ndarray]:
    """World rays (origins, directions) through pixel centres with alpha >= min_alpha."""
    k = ds.intrinsics
    os_, ds_ = [], []
    for i in views:
        v, u = np.nonzero(ds.alpha[i] >= min_alpha)
        d_cam = np.stack([(u + 0.5 - k.cx) / k.fx, (v + 0.5 - k.cy) / k.fy, np.ones(len(u))], -1)
        ds_.append(d_cam @ ds.poses[i, :3, :3].T)
        os_.append(np.broadcast_to(ds.poses[i, :3, 3], ds_[-1].shape))
    return np.concatenate(os_), np.concatenate(ds_)


@pytest.fixture(scope="module")
def box_ds(box_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    """The box scene imported at its own size (48 px)."""
    out = tmp_path_factory.mktemp("box") / "d.h5"
    return open_dataset(import_blender(box_scene, out, resolution=48, progress=False))


def test_box_scene_import(box_scene: Path, box_ds: Dataset, box_truth: tuple) -> None:
    _, rgb = box_truth
    ds = box_ds
    assert ds.kind == "dataset" and ds.images.shape == (30, 48, 48, 3)
    assert (len(ds.indices("train")), len(ds.indices("val")), len(ds.indices("test"))) == (24, 0, 6)
    assert ds.names[0] == "train/r_0" and ds.names[24] == "test/r_0"
    assert ds.source_index[24] == 0
    f = 48 / (2 * np.tan(0.4))
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == pytest.approx((f, f, 24, 24, 48, 48))
    assert ds.background == (1.0, 1.0, 1.0)
    np.testing.assert_array_equal(ds.normalization, np.eye(4))
    opaque = ds.alpha == 255
    assert set(np.unique(ds.alpha)) == {0, 255} and opaque.any()
    # straight colour, not composited onto the white background
    assert (ds.images[opaque] == rgb).all()
    assert (ds.images[~opaque] == 0).all()
    js = hashlib.sha256((box_scene / "transforms_train.json").read_bytes()).hexdigest()
    assert ds.provenance["inputs"]["transforms_train.json"] == js
    assert ds.provenance["params"]["resolution"] == 48


def test_carved_aabb_contains_and_fits_the_box(box_ds: Dataset, box_truth: tuple) -> None:
    box, _ = box_truth
    ds = box_ds
    assert ds.attrs["bounds_from"] == "alpha carving"
    assert (ds.aabb[0] <= box[0]).all() and (ds.aabb[1] >= box[1]).all()
    # the visual hull of 24 views is a little larger than the box; the margin is 2 %
    assert (box[0] - ds.aabb[0]).max() < 0.1 and (ds.aabb[1] - box[1]).max() < 0.1
    # every opaque pixel's ray (here: pixels of the test views, not used for carving) hits it
    o, d = opaque_rays(ds, ds.indices("test"), 255)
    assert len(o) > 100 and ray_hits_box(o, d, ds.aabb).all()
    # near/far bracket the AABB's corners along each optical axis
    corners = np.stack(np.meshgrid(*ds.aabb.T, indexing="ij"), -1).reshape(8, 3)
    z = np.einsum("nkj,nj->nk", corners[None] - ds.poses[:, None, :3, 3], ds.poses[:, :3, 2])
    np.testing.assert_allclose(ds.near_far, np.stack([z.min(1), z.max(1)], -1))


def test_downscaled_import_keeps_straight_colour_and_partial_alpha(
    box_scene: Path, box_truth: tuple, tmp_path: Path
) -> None:
    ds = open_dataset(import_blender(box_scene, tmp_path / "d.h5", resolution=24, progress=False))
    assert ds.images.shape[1:] == (24, 24, 3) and ds.intrinsics.fx == pytest.approx(
        12 / np.tan(0.4)
    )
    partial = (ds.alpha > 0) & (ds.alpha < 255)
    assert partial.any()
    # area resize of premultiplied colour: edge pixels keep the object's colour, no dark fringe
    diff = np.abs(ds.images[ds.alpha > 0].astype(int) - box_truth[1])
    assert diff.max() <= 1


def test_gray_import_uses_bt601_luma(box_scene: Path, tmp_path: Path) -> None:
    out = import_blender(box_scene, tmp_path / "g.h5", resolution=48, color="gray", progress=False)
    ds = open_dataset(out)
    assert ds.images.shape == (30, 48, 48, 1) and ds.background == (1.0,)
    # 0.299*200 + 0.587*30 + 0.114*60 = 84.25
    assert set(np.unique(ds.images[ds.alpha == 255])) == {84}


def test_opaque_images_fall_back_to_the_lookat_cube(scene_maker, tmp_path: Path) -> None:
    scene = scene_maker(tmp_path / "opaque", size=32, n_train=12, n_test=2)
    for png in scene.rglob("*.png"):
        im = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        im[:, :, 3] = 255
        cv2.imwrite(str(png), im)
    ds = open_dataset(import_blender(scene, tmp_path / "d.h5", resolution=32, progress=False))
    assert ds.attrs["bounds_from"].startswith("look-at cube")
    # cameras at distance 3 look at the origin; half fov 0.4 rad: half-size 3 sin(0.4)
    r = 3 * np.sin(0.4)
    np.testing.assert_allclose(ds.aabb, [[-r] * 3, [r] * 3], atol=1e-6)


@pytest.mark.parametrize("damage", ["missing_image", "bad_json", "no_matrix", "no_train", "size"])
def test_bad_scenes_fail_with_one_line(scene_maker, tmp_path: Path, damage: str) -> None:
    scene = scene_maker(tmp_path / "s", size=16, n_train=4, n_test=2)
    if damage == "missing_image":
        (scene / "train" / "r_1.png").unlink()
    elif damage == "bad_json":
        (scene / "transforms_test.json").write_text("{not json")
    elif damage == "no_matrix":
        meta = json.loads((scene / "transforms_train.json").read_text())
        del meta["frames"][2]["transform_matrix"]
        (scene / "transforms_train.json").write_text(json.dumps(meta))
    elif damage == "no_train":
        (scene / "transforms_train.json").unlink()
    else:
        cv2.imwrite(str(scene / "test" / "r_0.png"), np.zeros((8, 8, 4), np.uint8))
    out = tmp_path / "d.h5"
    with pytest.raises(InputError) as err:
        import_blender(scene, out, resolution=16, progress=False)
    assert "\n" not in str(err.value) and str(scene) in str(err.value)
    assert not out.exists()


def test_cli_import_and_errors(
    box_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    assert (
        main(["import-blender", str(box_scene), "--workdir", str(tmp_path), "--resolution", "24"])
        == 0
    )
    assert open_dataset(tmp_path / "dataset.h5").hw == (24, 24)
    capsys.readouterr()
    assert main(["import-blender", str(tmp_path / "nowhere"), "-o", str(tmp_path / "x.h5")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nowhere" in err
    assert not (tmp_path / "x.h5").exists()


def test_lego_import(lego_h5: Path) -> None:
    ds = open_dataset(lego_h5)
    assert ds.images.shape == (400, 160, 160, 3) and ds.alpha.shape == (400, 160, 160)
    assert [int((ds.split == v).sum()) for v in SPLITS.values()] == [100, 100, 200]
    assert ds.attrs["bounds_from"] == "alpha carving"
    # every camera looks at the scene centre: its optical axis passes close to the origin
    o, z = ds.poses[:, :3, 3], ds.poses[:, :3, 2]
    miss = np.linalg.norm(o - np.einsum("ni,ni->n", o, z)[:, None] * z, axis=1)
    assert miss.max() < 0.2
    # lego fits in the [-1.5, 1.5]^3 cube the scenes are rendered in, and fills much of it
    assert (ds.aabb[0] > -1.5).all() and (ds.aabb[1] < 1.5).all()
    assert (ds.aabb[1] - ds.aabb[0]).min() > 1.0
    # a ray through an opaque pixel of any test view (not used for carving) hits the AABB
    o, d = opaque_rays(ds, ds.indices("test"), 128)
    assert len(o) > 100_000 and ray_hits_box(o, d, ds.aabb).all()
    assert (ds.near_far[:, 0] > 0).all() and (ds.near_far[:, 1] > ds.near_far[:, 0]).all()
