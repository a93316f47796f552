"""The one calibration loader: every accepted form, distortion kept, sizes and bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from dronecap.camera import Camera
from dronecap.camera.files import calibration_record, load_camera, write_calibration
from dronecap.errors import InputError

K = [[1000.0, 0.0, 650.0], [0.0, 1002.0, 470.0], [0.0, 0.0, 1.0]]
DIST = [-0.1, 0.02, 0.001, -0.002, 0.003]


def test_numbers_on_the_command_line_take_the_source_size():
    cam, origin = load_camera("500,500,320,240", (640, 480))
    assert (cam.fx, cam.cx, cam.width, cam.height, cam.model) == (500, 320, 640, 480, "PINHOLE")
    assert origin == "calibration"
    with pytest.raises(InputError, match="fx,fy,cx,cy"):
        load_camera("1,2,3", (640, 480))
    with pytest.raises(InputError, match="positive"):
        load_camera("-5,5,3,3", (640, 480))


def test_calibration_json_keeps_distortion_and_scales_to_half_resolution(tmp_path):
    path = tmp_path / "calib.json"
    path.write_text(json.dumps({"K": K, "distortion": DIST, "width": 1280, "height": 960}))
    cam, origin = load_camera(str(path), (640, 480))
    # A K matrix is OpenCV's (pixel centres at integers): cx 650 -> 650.5, cy 470 -> 470.5 in
    # dronecap's convention; half the resolution halves f and c; distortion unchanged.
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 501.0, 325.25, 235.25)
    assert cam.opencv_coeffs()[:5].tolist() == DIST and origin == "calibration"
    with pytest.raises(InputError, match="aspect"):
        load_camera(str(path), (640, 640))


def test_written_record_reads_back_the_same_camera(tmp_path):
    cam = Camera.from_opencv(np.array(K), DIST, 1280, 960)
    path = tmp_path / "out.json"
    write_calibration(path, calibration_record(cam, rms=0.3))
    doc = json.loads(path.read_text())
    assert doc["model"] == "pinhole" and doc["distortion"] == DIST and doc["rms"] == 0.3
    assert doc["K"] == K and doc["pixel_center_offset"] == 0.5  # K in dronecap's convention
    del doc["fx"]  # read through K, which the offset key marks as dronecap's
    path.write_text(json.dumps(doc))
    assert load_camera(str(path), (1280, 960))[0] == cam
    assert load_camera(str(path), (1280, 960))[0] == cam
    fish = Camera.from_opencv(np.array(K), [0.1, -0.01, 0.002, 0.0], 1280, 960, fisheye=True)
    write_calibration(path, calibration_record(fish))
    assert json.loads(path.read_text())["model"] == "fisheye"
    assert load_camera(str(path), (1280, 960))[0] == fish


def test_flight_json_is_told_apart_and_its_distortion_kept(tmp_path):
    path = tmp_path / "flight.json"
    intr = {"fx": 183.0, "fy": 183.0, "cx": 162.0, "cy": 150.0, "width": 324, "height": 244}
    path.write_text(json.dumps({"intrinsics": {**intr, "distortion": DIST}, "frames": []}))
    cam, origin = load_camera(str(path), (324, 244))
    assert origin == "flight.json" and cam.model == "FULL_OPENCV"
    assert cam.opencv_coeffs()[:5].tolist() == DIST


def test_opencv_yaml_and_xml_written_by_filestorage(tmp_path):
    for name in ("cam.yml", "cam.xml"):
        path = tmp_path / name
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 1280)
        fs.write("image_height", 960)
        fs.write("camera_matrix", np.array(K))
        fs.write("distortion_coefficients", np.array(DIST).reshape(5, 1))
        fs.release()
        cam, origin = load_camera(str(path), (640, 480))
        assert (cam.fx, cam.cx, cam.cy) == (500.0, 325.25, 235.25), name  # (650 + .5) / 2
        assert cam.opencv_coeffs()[:5].tolist() == DIST and origin == "calibration"


def test_fisheye_yaml(tmp_path):
    path = tmp_path / "fish.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("fisheye_model", 1)
    fs.write("camera_matrix", np.array(K) / 2)
    fs.write("distortion_coefficients", np.array([0.1, -0.02, 0.003, -0.001]))
    fs.release()
    cam, _ = load_camera(str(path), (640, 480))
    assert cam.is_fisheye and cam.distortion == (0.1, -0.02, 0.003, -0.001)


def test_bad_files_are_one_clear_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_camera(str(tmp_path / "missing.json"), (640, 480))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"K": K, "distortion": [0.1] * 14, "width": 1280, "height": 960}))
    with pytest.raises(InputError, match="distortion"):  # tilted model: never silently dropped
        load_camera(str(bad), (1280, 960))
    bad.write_text(json.dumps({"width": 1280}))
    with pytest.raises(InputError, match="intrinsics"):
        load_camera(str(bad), (1280, 960))
    yml = tmp_path / "empty.yml"
    yml.write_text("%YAML:1.0\nimage_width: 640\n")
    with pytest.raises(InputError, match="camera_matrix"):
        load_camera(str(yml), (640, 480))
    yml.write_text("not: [yaml")
    with pytest.raises(InputError, match="OpenCV"):
        load_camera(str(yml), (640, 480))


def test_ros_camera_info_yaml(tmp_path):
    """ROS camera_info YAML: plain {rows, cols, data} maps, OpenCV pixel convention."""
    path = tmp_path / "himax.yaml"
    path.write_text(
        "image_width: 324\nimage_height: 244\ncamera_name: himax\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [183.0, 0.0, 160.0, 0.0, 183.5, 150.0, 0.0, 0.0, 1.0]\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.08, 0.01, 0.0, 0.0, 0.0]\n"
    )
    cam, origin = load_camera(str(path), (324, 244))
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (183.0, 183.5, 160.5, 150.5)
    assert cam.model == "OPENCV" and cam.distortion == (-0.08, 0.01, 0.0, 0.0)  # k3 = 0
    path.write_text(path.read_text().replace("plumb_bob", "equidistant").replace(", 0.0]", "]"))
    assert load_camera(str(path), (324, 244))[0].is_fisheye


def test_opencv_storage_output_reads_back_and_is_opencv_convention(tmp_path):
    cam = Camera.from_opencv(np.array(K), DIST, 1280, 960)
    for name in ("calib.yml", "calib.xml"):
        path = tmp_path / name
        write_calibration(path, calibration_record(cam, rms=0.3))
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        k = fs.getNode("camera_matrix").mat()
        assert (k[0, 2], k[1, 2]) == (649.5, 469.5)  # OpenCV's convention: 650 - 0.5
        assert fs.getNode("avg_reprojection_error").real() == 0.3
        fs.release()
        assert load_camera(str(path), (1280, 960))[0] == cam
