"""``dronecap ingest --intrinsics`` stores the calibration's full camera in frames.h5."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets import open_dataset
from tests.capture.conftest import pan, write_video


def test_calibration_json_distortion_reaches_frames_h5(tmp_path):
    video = write_video(tmp_path / "pan.avi", pan(24, (320, 240), 3.0))
    calib = tmp_path / "calib.json"
    # Calibrated at 640x480 (twice the video); K is OpenCV's (centres at integers, +0.5 here):
    # fx 600 -> 300, cx 330.5 -> 165.25, cy 250.5 -> 125.25.
    k = [[600.0, 0, 330.0], [0, 604.0, 250.0], [0, 0, 1]]
    dist = [-0.1, 0.02, 0.001, 0.0, 0.0]
    calib.write_text(json.dumps({"K": k, "distortion": dist, "width": 640, "height": 480}))
    assert main(["ingest", str(video), "--intrinsics", str(calib), "--workdir", str(tmp_path)]) == 0
    ds = open_dataset(tmp_path / "frames.h5", kinds=("frames",))
    cam = ds.intrinsics
    assert ds.attrs["camera_source"] == "calibration"
    # Centre crop of 320x240: x0 = 40, 240x240 -> 160x160 (s = 2/3).
    s = 2 / 3
    assert cam.fx == pytest.approx(300 * s) and cam.fy == pytest.approx(302 * s)
    assert cam.cx == pytest.approx((165.25 - 40) * s) and cam.cy == pytest.approx(125.25 * s)
    assert cam.model == "OPENCV"  # k3 = 0: the 4-parameter model
    np.testing.assert_allclose(cam.opencv_coeffs(), dist[:4])


def test_no_intrinsics_says_none(tmp_path):
    video = write_video(tmp_path / "pan.avi", pan(24, (320, 240), 3.0))
    assert main(["ingest", str(video), "--workdir", str(tmp_path)]) == 0
    ds = open_dataset(tmp_path / "frames.h5", kinds=("frames",))
    assert ds.intrinsics is None and ds.attrs["camera_source"] == "none"


def test_wrong_aspect_calibration_is_one_line_and_no_output(tmp_path, capsys):
    video = write_video(tmp_path / "pan.avi", pan(24, (320, 240), 3.0))
    calib = tmp_path / "calib.json"
    calib.write_text(
        json.dumps({"K": [[500, 0, 320], [0, 500, 320], [0, 0, 1]], "size": [640, 640]})
    )
    assert main(["ingest", str(video), "--intrinsics", str(calib), "--workdir", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "aspect" in err[0] and str(calib) in err[0]
    assert not (tmp_path / "frames.h5").exists()


@pytest.mark.slow
def test_simulated_lens_reaches_frames_h5_through_flight_json(tmp_path):
    """simulate (distorted, off-centre lens) -> ingest: frames.h5 holds flight.json's camera
    through the centre crop and resize, distortion unchanged, camera_source "flight.json"."""
    from dronecap.camera import Camera
    from dronecap.capture.framing import make_framing

    video = tmp_path / "f.mp4"
    args = ["--frames", "6", "--distortion=-0.1,0.02", "--principal-offset", "0.05,-0.1"]
    assert main(["-q", "simulate", "-o", str(video), *args, "--size", "324x244"]) == 0
    assert main(["-q", "ingest", str(video), "--workdir", str(tmp_path)]) == 0
    intr = json.loads((tmp_path / "f.json").read_text())["intrinsics"]
    assert intr["distortion"][:2] == [-0.1, 0.02]
    k = np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]])
    source = Camera.from_opencv(k, intr["distortion"], 324, 244)
    expected = make_framing((324, 244), (160, 160), "center").camera(source)
    ds = open_dataset(tmp_path / "frames.h5", kinds=("frames",))
    assert ds.attrs["camera_source"] == "flight.json" and ds.intrinsics == expected
    # by hand: crop x0 = (324 - 244) / 2 = 40, s = 160 / 244
    assert ds.intrinsics.cx == pytest.approx((intr["cx"] - 40) * 160 / 244)
