"""The camera type against OpenCV itself: projection and undistortion round trips, corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dronecap.camera import Camera

# An AI-deck-like lens at 160x160 (k1 -0.1, off-centre principal point).
LENS = Camera(91.0, 91.5, 84.0, 70.0, 160, 160, "OPENCV", (-0.1, 0.02, 0.001, -0.0005))
FISH = Camera(100.0, 100.0, 80.0, 80.0, 160, 160, "OPENCV_FISHEYE", (0.05, -0.01, 0.002, 0.0))


@pytest.mark.parametrize("cam", [LENS, FISH, LENS.pinhole()])
def test_undistort_then_project_returns_the_pixel(cam):
    corners = np.array([[0.5, 0.5], [159.5, 0.5], [0.5, 159.5], [159.5, 159.5], [80.0, 80.0]])
    xy = cam.undistort_points(corners)
    xyz = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    back = cam.project(xyz)
    assert np.abs(back - corners).max() < 1e-3


def test_project_matches_cv2_project_points():
    rng = np.random.default_rng(0)
    xyz = np.concatenate([rng.uniform(-0.8, 0.8, (50, 2)), np.ones((50, 1))], 1) * 2.0
    ref, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), LENS.matrix(), LENS.opencv_coeffs())
    assert np.allclose(LENS.project(xyz), ref.reshape(-1, 2), atol=1e-9)


def test_corner_displacement_is_pixels_not_zero():
    """The lens moves the corner pixel's ray by several pixels against a pinhole."""
    d = LENS.pixel_directions()
    p = LENS.pinhole().pixel_directions()
    shift = np.abs(d[0, 0, :2] - p[0, 0, :2]) * np.array([LENS.fx, LENS.fy])
    assert shift.max() > 2.0
    assert d.shape == (160, 160, 3) and np.all(d[..., 2] == 1)


def test_colmap_models_map_to_opencv_vectors():
    sr = Camera(100, 100, 80, 80, 160, 160, "SIMPLE_RADIAL", (-0.05,))
    assert sr.opencv_coeffs().tolist() == [-0.05, 0, 0, 0]
    cam = Camera.from_opencv(LENS.matrix(), [-0.1, 0.02, 0.001, -0.0005, 0.003], 160, 160)
    assert cam.model == "FULL_OPENCV" and len(cam.distortion) == 8
    # OpenCV's usual 5-vector with k3 = 0 is the 4-parameter OPENCV model
    cam = Camera.from_opencv(LENS.matrix(), [-0.1, 0.02, 0.001, -0.0005, 0.0], 160, 160)
    assert cam.model == "OPENCV" and cam.distortion == (-0.1, 0.02, 0.001, -0.0005)
    assert Camera.from_opencv(LENS.matrix(), np.zeros(5), 160, 160).model == "PINHOLE"
    with pytest.raises(ValueError):
        Camera.from_opencv(LENS.matrix(), np.zeros(12) + 0.1, 160, 160)


@pytest.mark.parametrize(
    "cam",
    [
        Camera(float("inf"), 1, 1, 1, 10, 10),
        Camera(1, 1, float("nan"), 1, 10, 10),
        Camera(-1, 1, 1, 1, 10, 10),
        Camera(1, 1, 1, 1, 10, 10, "OPENCV", (0.1,)),
        Camera(1, 1, 1, 1, 10, 10, "KANNALA", ()),
        Camera(1, 1, 1, 1, 0, 10),
    ],
)
def test_bad_cameras_are_reported(cam):
    assert cam.problems()


def test_scaling_keeps_the_distortion():
    half = LENS.scaled_to(80, 80)
    assert half.distortion == LENS.distortion
    assert half.fx == pytest.approx(LENS.fx / 2) and half.cx == pytest.approx(LENS.cx / 2)
