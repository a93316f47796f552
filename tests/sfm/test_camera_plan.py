"""``--camera fixed|refine|estimate`` and ``--camera-from``: which camera COLMAP starts from."""

from __future__ import annotations

import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.camera.colmap import camera_from_colmap, colmap_camera
from dronecap.datasets.format import Dataset, write_dataset
from dronecap.errors import InputError
from dronecap.sfm.camera_plan import plan_camera

# an AI-deck-like camera at 160 px: principal point well off the centre row
AIDECK = Camera(91.0, 91.5, 81.2, 101.0, 160, 160, "OPENCV", (-0.08, 0.01, 0.001, -0.002))


def frames(camera: Camera | None, source: str | None) -> Dataset:
    ds = Dataset(images=np.zeros((3, 160, 160, 1), np.uint8), kind="frames", intrinsics=camera)
    if source is not None:
        ds.attrs["camera_source"] = source
    return ds


def test_auto_keeps_a_calibrated_camera_fixed_with_its_distortion():
    plan = plan_camera(frames(AIDECK, "calibration"), "auto")
    assert plan.mode == "fixed" and not plan.refine
    assert plan.camera == AIDECK
    model, params = plan.colmap()
    # COLMAP's OPENCV order: fx, fy, cx, cy, k1, k2, p1, p2; same pixel-centre convention
    assert model == "OPENCV"
    assert params == [91.0, 91.5, 81.2, 101.0, -0.08, 0.01, 0.001, -0.002]


def test_auto_estimates_without_a_camera():
    plan = plan_camera(frames(None, "none"), "auto")
    assert (plan.mode, plan.camera, plan.colmap()) == ("estimate", None, None)


def test_estimate_keeps_a_known_principal_point():
    plan = plan_camera(frames(AIDECK, "flight.json"), "estimate")
    assert plan.refine and plan.refine_after and plan.camera.model == "SIMPLE_RADIAL"
    model, params = plan.colmap()
    assert model == "SIMPLE_RADIAL"
    assert params[1:3] == [81.2, 101.0]  # not the image centre (80, 80)
    assert params[0] == pytest.approx(1.2 * 160)


def test_refine_starts_from_the_known_camera():
    plan = plan_camera(frames(AIDECK, "calibration"), "refine")
    assert plan.mode == "refine" and plan.refine_after and not plan.refine
    assert plan.camera == AIDECK


@pytest.mark.parametrize("mode", ["fixed", "refine"])
def test_fixed_or_refine_without_a_camera_is_refused(mode):
    with pytest.raises(InputError, match="needs a known camera"):
        plan_camera(frames(None, "none"), mode)


def test_one_focal_model_with_two_focal_lengths_becomes_opencv():
    k = Camera(100.0, 102.0, 80.5, 79.5, 160, 160, "SIMPLE_RADIAL", (-0.05,))
    assert colmap_camera(k) == ("OPENCV", [100.0, 102.0, 80.5, 79.5, -0.05, 0.0, 0.0, 0.0])
    k1 = Camera(100.0, 100.0, 80.5, 79.5, 160, 160, "SIMPLE_RADIAL", (-0.05,))
    assert colmap_camera(k1) == ("SIMPLE_RADIAL", [100.0, 80.5, 79.5, -0.05])


@pytest.mark.parametrize(
    "camera",
    [AIDECK, Camera(90, 90, 80, 80, 160, 120, "OPENCV_FISHEYE", (0.1, -0.01, 0.002, 0.0003))],
)
def test_colmap_round_trip_is_exact(camera):
    import pycolmap

    model, params = colmap_camera(camera)
    cam = pycolmap.Camera(model=model, width=camera.width, height=camera.height, params=params)
    back = camera_from_colmap(cam.model_name, cam.params, cam.width, cam.height)
    assert back == camera
    # and COLMAP projects a point where OpenCV (through dronecap.camera) does
    xyz = np.array([[0.3, -0.2, 1.0]])
    assert np.allclose(cam.img_from_cam(xyz), camera.project(xyz), atol=1e-9)


def test_camera_from_an_earlier_reconstruction_is_scaled_to_the_frames(tmp_path):
    posed = Dataset(
        images=np.zeros((3, 244, 324, 1), np.uint8),
        kind="posed",
        poses=np.tile(np.eye(4), (3, 1, 1)),
        intrinsics=Camera(183.0, 183.0, 160.0, 150.0, 324, 244, "RADIAL", (-0.09, 0.01)),
    )
    write_dataset(tmp_path / "posed.h5", posed)
    half = Dataset(images=np.zeros((3, 122, 162, 1), np.uint8), kind="frames")
    plan = plan_camera(half, "auto", tmp_path / "posed.h5")
    assert plan.mode == "fixed" and plan.source == str(tmp_path / "posed.h5")
    assert (plan.camera.fx, plan.camera.cx, plan.camera.cy) == (91.5, 80.0, 75.0)
    assert plan.camera.distortion == (-0.09, 0.01)
    square = Dataset(images=np.zeros((3, 160, 160, 1), np.uint8), kind="frames")
    with pytest.raises(InputError, match="different aspect ratio"):
        plan_camera(square, "auto", tmp_path / "posed.h5")


def test_refined_adds_a_second_radial_term_to_self_calibrated_cameras():
    """The final adjustment of --camera estimate: SIMPLE_RADIAL (f, cx, cy, k) becomes RADIAL
    (f, cx, cy, k, 0); a camera of another model is left as it is."""
    import pycolmap

    from dronecap.sfm.camera_plan import refined

    rec = pycolmap.Reconstruction()
    one = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 120.0, 160, 160)
    one.params = [120.0, 81.0, 79.0, -0.08]
    other = pycolmap.Camera.create_from_model_name(2, "PINHOLE", 100.0, 160, 160)
    rec.add_camera(one)
    rec.add_camera(other)
    refined(rec)
    assert rec.cameras[1].model_name == "RADIAL"
    assert list(rec.cameras[1].params) == pytest.approx([120.0, 81.0, 79.0, -0.08, 0.0])
    assert rec.cameras[2].model_name == "PINHOLE"
    assert list(rec.cameras[2].params) == pytest.approx([100.0, 100.0, 80.0, 80.0])


@pytest.mark.parametrize("second_term, model", [(False, "SIMPLE_RADIAL"), (True, "RADIAL")])
def test_final_adjustment_adds_k2_only_to_an_estimated_camera(tmp_path, second_term, model):
    """--camera refine keeps a calibrated SIMPLE_RADIAL camera's model in the final
    adjustment; --camera estimate (second_term) turns it into RADIAL."""
    import pycolmap

    from dronecap.sfm.repair import refine_camera_of

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 120.0, 160, 160)
    rec.add_camera(cam)
    (tmp_path / "in").mkdir()
    rec.write(tmp_path / "in")
    out = refine_camera_of(tmp_path / "in", tmp_path / "out", second_term)
    assert pycolmap.Reconstruction(out).cameras[1].model_name == model
