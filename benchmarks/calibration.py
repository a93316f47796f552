"""Calibration accuracy: OpenCV's reference results, and lenses known exactly (rendered boards).

    OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/calibration.py     # ~1 min

1. The reference sets in ../shared/data/calibration (chessboard left/right 640x480, 13 views each;
   ChArUco, 4 views) calibrated as ``dronecap calibrate`` does, against the reference JSONs
   (computed with OpenCV 5.0's standard recipe). Floors of issue 14: chessboard left within
   0.5 % of fx/fy, 1 px of cx/cy, 0.05 px of the RMS; ChArUco within 1 %. The references put
   pixel centres at integers (OpenCV); dronecap at +0.5, so 0.5 is subtracted from our cx, cy
   before comparing.
2. Chessboards rendered through a known 320x240 lens (the test suite's renderer: 8 views, squares
   of ~20 px, as a nano-drone camera sees a printed board): the error against the truth with
   OpenCV's 11-px refinement window and with ``--subpix-window 0`` (sized to the squares).
3. A 600-frame calibration video through the same lens (a board moving smoothly through 12 key
   poses, each rendered frame held 5 frames as a slow hand-held sweep at 30 Hz): how many views
   the video path keeps, why it drops the rest, its time and accuracy.

Single thread (``cv2.setNumThreads(1)``); times are medians of 3 runs. Writes
benchmarks/results/calibration.md and calibration_left.png.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the test suite's board renderer (tests/calibration/conftest.py)

from dronecap.calibration.calibrate import calibrate, find_boards  # noqa: E402
from dronecap.calibration.plot import plot_calibration  # noqa: E402
from dronecap.calibration.targets import Board  # noqa: E402
from dronecap.calibration.views import pick_video_views, read_images  # noqa: E402
from dronecap.camera import Camera  # noqa: E402
from tests.calibration.conftest import board_images, board_poses  # noqa: E402
from tests.capture.conftest import write_video  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "calibration"
RESULTS = ROOT / "benchmarks" / "results" / "calibration.md"
PLOT = RESULTS.with_name("calibration_left.png")  # coverage + per-view error, chessboard left
REPEATS = 3
LENS = Camera(300.0, 302.0, 165.0, 118.0, 320, 240, "OPENCV", (-0.25, 0.08, 0.001, -0.001))
FISHEYE = Camera(160.0, 160.0, 160.0, 120.0, 320, 240, "OPENCV_FISHEYE", (0.05, -0.01, 0, 0))


def timed(fn):
    """(result of the last run, median seconds of REPEATS runs)."""
    times, out = [], None
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def reference_rows() -> list[str]:
    chess = json.loads(
        (DATA / "opencv_chessboard" / "reference_calibration_opencv5.json").read_text()
    )
    charuco = json.loads(
        (DATA / "opencv_charuco" / "reference_calibration_opencv5.json").read_text()
    )
    std, auto = Board("chessboard", 9, 6), Board("chessboard", 9, 6, subpix_window=0)
    left, right = "opencv_chessboard/left*.jpg", "opencv_chessboard/right*.jpg"
    charuco_board = Board("charuco", 5, 7, 0.04, 0.02)
    cases = [
        ("chessboard left", left, std, chess["left"], 0.005),
        ("chessboard right", right, std, chess["right"], 0.005),
        ("chessboard left, --subpix-window 0", left, auto, chess["left"], None),
        ("chessboard right, --subpix-window 0", right, auto, chess["right"], None),
        ("ChArUco 5x7", "opencv_charuco/img_0*.jpg", charuco_board, charuco, 0.01),
    ]
    rows = []
    for name, pattern, board, ref, tol in cases:

        def run(pattern=pattern, board=board):
            views, rejected, size = find_boards(read_images([str(DATA / pattern)]), board)
            return calibrate(views, size, board, rejected=rejected)

        cal, seconds = timed(run)
        k, rk = cal.camera, np.array(ref["K"])
        dfx = 100 * (k.fx / rk[0, 0] - 1)
        dfy = 100 * (k.fy / rk[1, 1] - 1)
        dcx, dcy = k.cx - 0.5 - rk[0, 2], k.cy - 0.5 - rk[1, 2]
        drms = cal.rms - ref["rms"]
        if tol is None:
            verdict = "(not a floor)"
        elif tol == 0.005:
            ok = (
                max(abs(dfx), abs(dfy)) <= 0.5
                and max(abs(dcx), abs(dcy)) <= 1
                and abs(drms) <= 0.05
            )
            verdict = "yes" if ok else "NO"
        else:
            rel = [abs(dfx), abs(dfy), 100 * abs(dcx / rk[0, 2]), 100 * abs(dcy / rk[1, 2])]
            ok = max(rel) <= 1 and abs(drms / ref["rms"]) <= 0.01
            verdict = "yes" if ok else "NO"
        rows.append(
            f"| {name} | {len(cal.view_errors)} | {k.fx:.2f} | {k.fy:.2f} | {k.cx - 0.5:.2f} | "
            f"{k.cy - 0.5:.2f} | {cal.rms:.3f} | {dfx:+.3f} % | {dfy:+.3f} % | {dcx:+.3f} | "
            f"{dcy:+.3f} | {drms:+.4f} | {verdict} | {seconds:.2f} |"
        )
    return rows


def ray_error(got: Camera, true: Camera) -> float:
    """Largest pixel error when rays of ``got`` through a 3x3 grid (15/50/85 % of the image)
    are projected through ``true``."""
    w, h = true.width, true.height
    uv = np.array([[f * w, g * h] for f in (0.15, 0.5, 0.85) for g in (0.15, 0.5, 0.85)])
    xy = got.undistort_points(uv)
    return float(np.abs(true.project(np.c_[xy, np.ones(len(xy))]) - uv).max())


def synthetic_rows() -> list[str]:
    rows = []
    for lens, model, distance in ((LENS, "pinhole", 15.0), (FISHEYE, "fisheye", 8.0)):
        images = board_images(lens, board_poses(8, distance=distance))
        for window in (11, 0):
            board = Board("chessboard", 9, 6, subpix_window=window)

            def run(board=board, images=images, model=model):
                named = [(f"v{i}", im) for i, im in enumerate(images)]
                views, rejected, size = find_boards(named, board)
                return calibrate(views, size, board, model, rejected)

            cal, seconds = timed(run)
            k = cal.camera
            rows.append(
                f"| {model} f={lens.fx:.0f} | {window or 'auto (0)'} | {len(cal.view_errors)} | "
                f"{100 * (k.fx / lens.fx - 1):+.2f} % | {100 * (k.fy / lens.fy - 1):+.2f} % | "
                f"{k.cx - lens.cx:+.2f} | {k.cy - lens.cy:+.2f} | {ray_error(k, lens):.2f} | "
                f"{cal.rms:.3f} | {seconds:.2f} |"
            )
    return rows


def video_rows() -> list[str]:
    keys = board_poses(12, seed=2)
    poses = []
    for (r0, t0), (r1, t1) in zip(keys, keys[1:] + keys[:1], strict=True):
        for a in np.linspace(0, 1, 10, endpoint=False):
            poses.append(((1 - a) * r0 + a * r1, (1 - a) * t0 + a * t1))
    frames = [img for img in board_images(LENS, poses) for _ in range(5)]
    board = Board("chessboard", 9, 6, subpix_window=0)
    with tempfile.TemporaryDirectory() as tmp:
        video = write_video(Path(tmp) / "board.avi", frames)

        def run():
            views, rejected, size, decoded = pick_video_views(video, board, progress=False)
            return calibrate(views, size, board, rejected=rejected), decoded

        (cal, decoded), seconds = timed(run)
    why = Counter(r.split(" (")[0].split(" of ")[0] for r in cal.rejected.values())
    k = cal.camera
    return [
        f"| {decoded} | {len(cal.view_errors)} | "
        + ", ".join(f"{n} {c}" for n, c in why.most_common())
        + f" | {100 * (k.fx / LENS.fx - 1):+.2f} % | {k.cx - LENS.cx:+.2f} | "
        f"{k.cy - LENS.cy:+.2f} | {ray_error(k, LENS):.2f} | {cal.rms:.3f} | {seconds:.1f} |"
    ]


def main() -> None:
    cv2.setNumThreads(1)
    if not DATA.exists():
        sys.exit(f"calibration data not found at {DATA}")
    load = os.getloadavg()
    ref = reference_rows()
    board = Board("chessboard", 9, 6)
    views, rejected, size = find_boards(
        read_images([str(DATA / "opencv_chessboard/left*.jpg")]), board
    )
    plot_calibration(calibrate(views, size, board, rejected=rejected), views, PLOT)
    syn = synthetic_rows()
    vid = video_rows()
    text = "\n".join(
        [
            "# Calibration accuracy",
            "",
            "Command: `OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/calibration.py` "
            f"(OpenCV {cv2.__version__}, one thread; load average during the run "
            f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on 2 cores shared with other jobs; "
            f"times are medians of {REPEATS} runs of detection + calibration).",
            "",
            "## Against OpenCV's reference calibrations (../shared/data/calibration)",
            "",
            "cx, cy are given in OpenCV's pixel convention (ours - 0.5) to compare with the "
            "references. Floors (issue 14): chessboard within 0.5 % of fx/fy, 1 px of cx/cy, "
            "0.05 px of the RMS; ChArUco within 1 %.",
            "",
            "| set | views | fx | fy | cx | cy | RMS px | d fx | d fy | d cx px | d cy px "
            "| d RMS px | floor met | s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
            *ref,
            "",
            f"![chessboard left: corners and per-view error]({PLOT.name})",
            "",
            "With `--subpix-window 0` the corner refinement window is 0.4 x the corner spacing "
            "instead of OpenCV's fixed 11 px: the RMS drops (left02/right02, whose squares are "
            "~20 px, stop being pulled towards neighbouring corners) and fx moves by ~0.5 %; "
            "the default stays OpenCV's recipe, which the references use, and "
            "`dronecap calibrate` warns when a view's squares are smaller than the window.",
            "",
            "## Against lenses known exactly (boards rendered through them, 320x240, 8 views)",
            "",
            "Errors are ours - truth (dronecap pixel convention on both sides); 'ray error' is "
            "the largest pixel error of rays through a 3x3 grid at 15/50/85 % of the image "
            "(where the boards were) projected through the true lens.",
            "",
            "| lens | window | views | d fx | d fy | d cx px | d cy px | ray error px | RMS px "
            "| s |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *syn,
            "",
            "## A calibration video (600 frames, 120 distinct board poses, MJPG, auto window)",
            "",
            "| frames | views used | dropped (reason count) | d fx | d cx px | d cy px "
            "| ray error px | RMS px | s (scan + solve) |",
            "|---|---|---|---|---|---|---|---|---|",
            *vid,
            "",
        ]
    )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
