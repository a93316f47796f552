"""`dronecap import-colmap`: a pycolmap model of lego views imports with all its registered
images, poses and camera exact through the normalisation and the resize; refusals."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from dronecap.cli import main
from dronecap.datasets.format import open_dataset
from dronecap.datasets.import_colmap import import_colmap
from dronecap.errors import InputError

from .interop import lego_colmap_model


@pytest.fixture(scope="module")
def lego_model(lego_h5: Path, tmp_path_factory: pytest.TempPathFactory):
    """(folder with sparse/ and images/, the similarity to the COLMAP frame, frames used)."""
    root = tmp_path_factory.mktemp("colmap")
    s, idx = lego_colmap_model(open_dataset(lego_h5), root)
    return root, s, idx


def test_every_registered_image_imports_exactly(lego_model, lego_h5: Path, tmp_path: Path):
    root, s, idx = lego_model
    out = tmp_path / "w"
    args = ["import-colmap", str(root / "sparse"), str(root / "images"), "--size", "80"]
    assert main([*args, "--workdir", str(out)]) == 0
    ds = open_dataset(out / "dataset.h5")
    lego = open_dataset(lego_h5)
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    assert ds.n == rec.num_reg_images() == len(idx)
    assert ds.names == sorted(f"r_{f:03d}.png" for f in idx)
    # the camera: 160 -> 80 px halves every focal length and principal point, nothing else
    k = lego.intrinsics
    assert (ds.intrinsics.fx, ds.intrinsics.cx, ds.intrinsics.width) == (k.fx / 2, k.cx / 2, 80)
    # poses: the dataset's normalisation after the model's similarity takes lego's poses to ours
    m = ds.normalization @ s
    scale = np.cbrt(np.linalg.det(m[:3, :3]))
    order = np.argsort([f"r_{f:03d}.png" for f in idx])
    want = lego.poses[idx][order]
    np.testing.assert_allclose(ds.poses[:, :3, :3], m[:3, :3] / scale @ want[:, :3, :3], atol=1e-6)
    np.testing.assert_allclose(ds.poses[:, :3, 3], want[:, :3, 3] @ m[:3, :3].T + m[:3, 3],
                               atol=1e-6)  # fmt: skip
    # every observation reprojects through the stored camera and pose onto its (halved) keypoint
    norm = ds.normalization
    for i, name in enumerate(ds.names):
        image = rec.find_image_with_name(name)
        for p2 in image.points2D:
            x = norm[:3, :3] @ rec.points3D[p2.point3D_id].xyz + norm[:3, 3]
            uv = ds.intrinsics.project(((x - ds.poses[i, :3, 3]) @ ds.poses[i, :3, :3])[None])[0]
            np.testing.assert_allclose(uv, p2.xy / 2, atol=1e-3)
    # bounds as for a flight: the box holds every camera and the kept points; near < far
    c = ds.poses[:, :3, 3]
    assert (c >= ds.aabb[0]).all() and (c <= ds.aabb[1]).all()
    assert (ds.near_far[:, 0] < ds.near_far[:, 1]).all()
    pts = ds.extra["points3d_xyz"]
    assert 0 < len(pts) <= rec.num_points3D() and ds.extra["points3d_rgb"].shape == pts.shape
    assert ds.channels == 3 and len(ds.indices("test")) == 3  # every 8th of 24


def test_gray_option(lego_model, tmp_path: Path):
    root, _, idx = lego_model
    ds = open_dataset(
        import_colmap(
            root / "sparse", root / "images", tmp_path / "g.h5", color="gray", progress=False
        )  # fmt: skip
    )
    assert ds.channels == 1 and ds.n == len(idx) and ds.hw == (160, 160)


def test_refusals(lego_model, tmp_path: Path, capsys: pytest.CaptureFixture):
    root, _, _ = lego_model
    with pytest.raises(InputError, match="not a COLMAP model folder"):
        import_colmap(root / "images", root / "images", tmp_path / "d.h5", progress=False)
    images = tmp_path / "images"
    shutil.copytree(root / "images", images)
    next(images.glob("r_*.png")).unlink()
    with pytest.raises(InputError, match="missing or unreadable image"):
        import_colmap(root / "sparse", images, tmp_path / "d.h5", progress=False)
    assert main(["import-colmap", str(tmp_path / "nope"), str(images), "-o",
                 str(tmp_path / "d.h5")]) == 1  # fmt: skip
    err = capsys.readouterr().err
    assert "no such folder" in err and err.count("\n") == 1


def test_several_cameras_give_a_camera_per_frame(lego_model, tmp_path: Path) -> None:
    """COLMAP's several cameras (one image on a second camera) import as a camera table."""
    root, _, _ = lego_model
    images = tmp_path / "images"
    shutil.copytree(root / "images", images)
    shutil.copyfile(next(images.glob("r_*.png")), images / "r_999.png")
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    cam = pycolmap.Camera(model="PINHOLE", width=160, height=160, params=[100, 100, 80, 80])
    cam.camera_id = 2
    rec.add_camera_with_trivial_rig(cam)
    image = pycolmap.Image(name="r_999.png", camera_id=2, image_id=99)
    rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d())
    two = tmp_path / "two"
    two.mkdir()
    rec.write_binary(str(two))
    ds = open_dataset(import_colmap(two, images, tmp_path / "d.h5", size=80, progress=False))
    assert len(ds.cameras) == 2 and ds.intrinsics is None
    last = ds.names.index("r_999.png")
    assert ds.camera_of(last).fx == pytest.approx(50.0) and ds.camera_of(0).fx != 50.0
    assert (ds.camera_index == 1).sum() == 1
