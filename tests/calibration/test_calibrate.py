"""``dronecap calibrate``: OpenCV reference results, a known synthetic lens, a video, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.calibration.calibrate import calibrate, find_boards
from dronecap.calibration.targets import Board
from dronecap.camera import Camera
from dronecap.cli import main
from tests.calibration.conftest import board_images, board_poses
from tests.capture.conftest import write_video
from tests.conftest import SHARED_DATA

CALIB_DATA = SHARED_DATA / "calibration"
CHESS = CALIB_DATA / "opencv_chessboard"
CHARUCO = CALIB_DATA / "opencv_charuco"
# A 320x240 lens like a nano-drone camera's: off-centre principal point, barrel distortion.
LENS = Camera(300.0, 302.0, 165.0, 118.0, 320, 240, "OPENCV", (-0.25, 0.08, 0.001, -0.001))
FISHEYE = Camera(160.0, 160.0, 160.0, 120.0, 320, 240, "OPENCV_FISHEYE", (0.05, -0.01, 0, 0))
AUTO = Board("chessboard", 9, 6, subpix_window=0)  # squares of ~20 px need a smaller window


def calibrate_cli(tmp_path: Path, *args: str) -> tuple[int, dict | None]:
    out = tmp_path / "calib.json"
    rc = main(["calibrate", *args, "-o", str(out)])
    return rc, json.loads(out.read_text()) if out.exists() else None


def reference(path: Path) -> dict:
    if not path.exists():
        pytest.skip(f"calibration reference data not found at {path.parent} (../shared/data)")
    return json.loads(path.read_text())


def near_reference(got: dict, ref: dict, **tolerance: dict) -> None:
    """Assert our calibration ``got`` matches OpenCV's ``ref`` (K, rms): each of fx, fy, cx, cy
    and rms named in ``tolerance`` within its ``pytest.approx`` keywords. The reference is in
    OpenCV's pixel convention (centres at integers); ours adds 0.5."""
    k = np.array(ref["K"])
    theirs = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "rms": ref["rms"]}
    ours = {**got, "cx": got["cx"] - 0.5, "cy": got["cy"] - 0.5}
    for name, tol in tolerance.items():
        assert ours[name] == pytest.approx(theirs[name], **tol), name


def test_chessboard_left_matches_opencv_reference(tmp_path):
    ref = reference(CHESS / "reference_calibration_opencv5.json")["left"]
    rc, got = calibrate_cli(
        tmp_path, str(CHESS / "left*.jpg"), "--pattern", "chessboard", "--board", "9x6"
    )
    assert rc == 0 and len(got["views_used"]) == ref["found"] == 13
    focal, centre = {"rel": 0.005}, {"abs": 1.0}
    near_reference(got, ref, fx=focal, fy=focal, cx=centre, cy=centre, rms={"abs": 0.05})
    assert got["model"] == "pinhole" and len(got["distortion"]) == 5
    assert got["width"] == 640 and got["height"] == 480


def test_charuco_matches_opencv_reference(tmp_path):
    ref = reference(CHARUCO / "reference_calibration_opencv5.json")
    rc, got = calibrate_cli(
        tmp_path,
        *sorted(str(p) for p in CHARUCO.glob("img_0*.jpg")),
        *("--pattern", "charuco", "--board", "5x7", "--square", "0.04", "--marker", "0.02"),
    )
    assert rc == 0 and len(got["views_used"]) == ref["n_views"] == 4
    near_reference(got, ref, **dict.fromkeys(("fx", "fy", "cx", "cy", "rms"), {"rel": 0.01}))
    # Four views leave k2, k3 loose and the lower-right corner of the image without a corner.
    assert any("poorly constrained" in w for w in got["warnings"])
    assert any("bottom-right corner" in w for w in got["warnings"])


@pytest.fixture(scope="module")
def lens_images():
    return [(f"v{i}", im) for i, im in enumerate(board_images(LENS, board_poses(8)))]


def same_rays(got: Camera, true: Camera, tol_px: float) -> None:
    """Rays through a 3x3 grid of pixels (15 %, 50 %, 85 % of the width and height: where the
    boards were; beyond them the fit extrapolates) of ``got`` project through ``true`` to the
    same pixels (the distortion that matters, whatever the individual coefficients)."""
    w, h = true.width, true.height
    uv = np.array([[f * w, g * h] for f in (0.15, 0.5, 0.85) for g in (0.15, 0.5, 0.85)])
    xy = got.undistort_points(uv)
    np.testing.assert_allclose(true.project(np.c_[xy, np.ones(len(xy))]), uv, atol=tol_px)


def test_known_lens_is_recovered_in_dronecap_pixel_convention(lens_images):
    """Images rendered through LENS (pixel centres at +0.5): the calibration gives LENS back."""
    views, rejected, size = find_boards(lens_images, AUTO)
    assert size == (320, 240) and len(views) == 8 and not rejected
    cal = calibrate(views, size, AUTO)
    k = cal.camera
    assert k.fx == pytest.approx(300.0, rel=0.005) and k.fy == pytest.approx(302.0, rel=0.005)
    assert k.cx == pytest.approx(165.0, abs=0.6) and k.cy == pytest.approx(118.0, abs=0.6)
    assert k.opencv_coeffs()[0] == pytest.approx(-0.25, abs=0.01)
    assert cal.rms < 0.2
    same_rays(k, LENS, 0.75)


def test_large_window_on_small_squares_is_warned_about(lens_images):
    board = Board("chessboard", 9, 6)  # default 11-px half-window, squares ~20 px
    views, _, size = find_boards(lens_images, board)
    cal = calibrate(views, size, board)
    assert any("subpix_window 0" in w for w in cal.warnings)


def test_fisheye_lens_is_recovered():
    images = board_images(FISHEYE, board_poses(8, distance=8.0))
    views, _, size = find_boards(((f"v{i}", im) for i, im in enumerate(images)), AUTO)
    cal = calibrate(views, size, AUTO, model="fisheye")
    k = cal.camera
    assert k.is_fisheye and k.fx == pytest.approx(160.0, rel=0.005)
    assert k.cx == pytest.approx(160.0, abs=0.5) and k.cy == pytest.approx(120.0, abs=0.5)
    same_rays(k, FISHEYE, 0.75)


def test_video_gives_one_view_per_pose_and_drops_blurry_frames(tmp_path, capsys):
    poses = board_poses(6, seed=1)
    frames = []
    for img in board_images(LENS, poses):
        frames += [img] * 4 + [cv2.GaussianBlur(img, (0, 0), 3.0)] * 2  # lingering, then moving
    video = write_video(tmp_path / "board.avi", frames)
    rc, got = calibrate_cli(
        tmp_path, "--video", str(video), "--pattern", "chessboard", "--board", "9x6",
        "--subpix-window", "0",
    )  # fmt: skip
    assert rc == 0
    assert len(got["views_used"]) == 6  # 36 frames, 6 distinct poses
    reasons = list(got["rejected"].values())
    assert sum(r.startswith("blurry") for r in reasons) >= 6
    assert sum(r.startswith("near-duplicate") for r in reasons) >= 12
    assert got["fx"] == pytest.approx(300.0, rel=0.01)


def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys):
    rng = np.random.default_rng(0)
    noise = tmp_path / "noise"
    noise.mkdir()
    for i in range(3):
        cv2.imwrite(str(noise / f"n{i}.png"), rng.integers(0, 255, (120, 160), np.uint8))
    board = ("--pattern", "chessboard", "--board", "9x6")

    def fails(*args: str, match: str) -> None:
        rc, got = calibrate_cli(tmp_path, *args)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 1 and got is None and len(err) == 1 and match in err[0], err

    fails(str(noise), *board, match="no chessboard 9x6 board found in any of the 3 images")
    one = board_images(LENS, board_poses(1))[0]
    cv2.imwrite(str(tmp_path / "one.png"), one)
    fails(str(tmp_path / "one.png"), *board, match="found in only 1 of 1 images")
    cv2.imwrite(str(tmp_path / "big.png"), cv2.resize(one, (640, 480)))
    fails(str(tmp_path / "one.png"), str(tmp_path / "big.png"), *board, match="640x480")
    fails(str(noise), "--pattern", "chessboard", "--board", "9", match="--board must be WxH")
    fails(str(noise), "--pattern", "charuco", "--board", "5x7", match="marker must be positive")
    fails(str(tmp_path / "missing*.png"), *board, match="no calibration images")
    fails(*board, match="give calibration images or --video")


def test_aruco_grid_through_a_known_pinhole(tmp_path):
    """An ArUco grid drawn by OpenCV, viewed through K (dronecap convention) by homographies."""
    board = Board("aruco-grid", 4, 5, marker=0.04, gap=0.01)
    scale, margin = 2000.0, 20  # generated image: px per board unit, border px
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    grid = cv2.aruco.GridBoard((4, 5), 0.04, 0.01, d)
    art = grid.generateImage((380 + 2 * margin, 480 + 2 * margin), marginSize=margin)
    k = np.array([[400.0, 0, 330.0], [0, 400.0, 236.0], [0, 0, 1]])
    # art pixel index i (centre i + .5) -> board unit (i + .5 - margin) / scale
    off = (0.5 - margin) / scale
    art_to_board = np.array([[1 / scale, 0, off], [0, 1 / scale, off], [0, 0, 1]])
    to_opencv_px = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    names = []
    for i, (rvec, tvec) in enumerate(board_poses(6)):
        r, _ = cv2.Rodrigues(rvec)
        # the chessboard poses scaled by 0.025 (board middle 0.375 m away), grid middle there
        t = (tvec + r @ np.array([4.0, 2.5, 0])) * 0.025 - r @ np.array([0.095, 0.12, 0])
        h = to_opencv_px @ k @ np.c_[r[:, :2], t] @ art_to_board
        view = cv2.warpPerspective(art, h, (640, 480), flags=cv2.INTER_AREA, borderValue=160)
        names.append(str(tmp_path / f"g{i}.png"))
        cv2.imwrite(names[-1], view)
    rc, got = calibrate_cli(
        tmp_path, *names, "--pattern", "aruco-grid", "--board", "4x5", "--marker", "0.04",
        "--gap", "0.01", "--plot", str(tmp_path / "calib.png"),
    )  # fmt: skip
    assert cv2.imread(str(tmp_path / "calib.png")) is not None  # the coverage/error plot
    assert rc == 0 and len(got["views_used"]) == 6 and got["target"] == board.record()
    assert got["fx"] == pytest.approx(400.0, rel=0.01) and got["fy"] == pytest.approx(400, rel=0.01)
    assert got["cx"] == pytest.approx(330.0, abs=1.5) and got["cy"] == pytest.approx(236.0, abs=1.5)


def test_a_view_with_large_error_is_rejected_and_the_rest_solved_again(lens_images):
    from dataclasses import replace

    from dronecap.calibration.calibrate import View

    views, _, size = find_boards(lens_images, AUTO)
    rng = np.random.default_rng(0)
    bad = views[0].detection
    noisy = bad.image_points + rng.normal(0, 4.0, bad.image_points.shape).astype(np.float32)
    views[0] = View("bent", replace(bad, image_points=noisy))  # ~5.7 px RMS of corner noise
    cal = calibrate(views, size, AUTO)
    assert cal.rejected["bent"].startswith("large error")
    assert "bent" not in cal.view_errors and len(cal.view_errors) == 7
    assert cal.rms < 0.2 and cal.camera.fx == pytest.approx(300.0, rel=0.005)
