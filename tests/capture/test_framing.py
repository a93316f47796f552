"""Crop, resize and camera maths, worked out by hand."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.capture.framing import make_framing, parse_size, to_gray


def test_center_crop_of_640x480_and_its_intrinsics():
    f = make_framing((640, 480), (160, 160), "center")
    assert f.box == (80, 0, 480, 480)  # (640 - 480) / 2 = 80 cut on each side
    assert f.scale == (1 / 3, 1 / 3)  # 160 / 480
    cam = f.camera(Camera(500.0, 510.0, 320.0, 240.0, 640, 480))
    # fx' = 500 / 3, cx' = (320 - 80) / 3 = 80, cy' = 240 / 3 = 80
    assert cam.fx == pytest.approx(500 / 3)
    assert cam.fy == pytest.approx(170.0)
    assert (cam.cx, cam.cy) == (pytest.approx(80.0), pytest.approx(80.0))
    assert (cam.width, cam.height) == (160, 160)


def test_odd_source_161x97_crops_then_upsamples():
    f = make_framing((161, 97), (160, 160), "center")
    assert f.box == (32, 0, 97, 97)  # (161 - 97) // 2 = 32
    assert f.upsamples
    cam = f.camera(Camera(100.0, 100.0, 80.5, 48.5, 161, 97))
    s = 160 / 97
    assert cam.cx == pytest.approx((80.5 - 32) * s)  # = 48.5 * s = 80: centre stays centre
    assert cam.cx == pytest.approx(80.0)
    assert cam.fx == pytest.approx(100 * s)


def test_tall_frame_crops_top_and_bottom_and_stretch_keeps_all():
    assert make_framing((90, 200), (160, 160), "center").box == (0, 55, 90, 90)
    f = make_framing((320, 240), (160, 160), "stretch")
    assert f.box == (0, 0, 320, 240) and f.scale == (0.5, 2 / 3)
    assert make_framing((320, 240), (160, 160), "10,20,200,200").box == (10, 20, 200, 200)
    with pytest.raises(ValueError):
        make_framing((320, 240), (160, 160), "100,100,300,300")


def test_a_point_lands_where_the_intrinsics_say():
    """A bright dot at source pixel centre (u, v) ends up at ((u + .5 - x0) s - .5) in output."""
    img = np.zeros((480, 640), np.uint8)
    u, v = 401, 133  # pixel centre at (401.5, 133.5) in continuous coordinates
    img[v - 1 : v + 2, u - 1 : u + 2] = 255  # symmetric 3x3 blob around that centre
    f = make_framing((640, 480), (160, 160), "center")
    out = f.apply(img).astype(float)
    ys, xs = np.mgrid[0:160, 0:160]
    cu, cv = (out * xs).sum() / out.sum() + 0.5, (out * ys).sum() / out.sum() + 0.5
    assert cu == pytest.approx((401.5 - 80) / 3, abs=0.05)  # 107.17
    assert cv == pytest.approx(133.5 / 3, abs=0.05)  # 44.5


def test_gray_uses_bt601_luma():
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 2] = 200  # pure red
    assert to_gray(bgr)[0, 0] == round(0.299 * 200)  # 60
    assert to_gray(np.full((2, 2), 1000, np.uint16))[0, 0] == 1000 >> 8


def test_parse_size():
    assert parse_size("160") == (160, 160)
    assert parse_size("200x120") == (200, 120)


def test_area_resize_is_what_cv2_does():
    img = (np.arange(240 * 320) % 251).astype(np.uint8).reshape(240, 320)
    f = make_framing((320, 240), (160, 160), "center")
    expected = cv2.resize(img[:, 40:280], (160, 160), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(f.apply(img), expected)


def test_distorted_point_through_crop_and_resize_lands_where_the_stored_camera_projects():
    """A 3D point projected by the 640x480 source camera (OpenCV, with distortion), moved by the
    crop (-x0) and the resize (x s), must be where the 160x160 camera projects it."""
    src = Camera(500.0, 505.0, 330.0, 230.0, 640, 480, "OPENCV", (-0.2, 0.05, 1e-3, -2e-3))
    f = make_framing((640, 480), (160, 160), "center")
    out = f.camera(src)
    assert out.distortion == src.distortion and (out.width, out.height) == (160, 160)
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)]
    k = src.matrix()
    uv_src, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), k, src.opencv_coeffs())
    x0, y0, w, h = f.box  # (80, 0, 480, 480)
    expected = (uv_src.reshape(-1, 2) - [x0, y0]) * [160 / w, 160 / h]
    np.testing.assert_allclose(out.project(xyz), expected, atol=1e-6)
