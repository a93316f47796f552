"""Report helpers: dropped-frame runs placed in the flight, reasons, printing."""

from __future__ import annotations

import numpy as np

from dronecap.sfm.report import drop_reason, dropped_runs, format_report, pose_jumps


def test_dropped_runs_group_and_place_by_hand():
    # 11 frames (0..10); dropped 0, 1 | 5 | 9, 10
    runs = dropped_runs(np.array([0, 1, 5, 9, 10]), 11)
    assert [(r["first"], r["last"], r["count"]) for r in runs] == [(0, 1, 2), (5, 5, 1), (9, 10, 2)]
    # run centres: 0.5 / 10 = 5%, 5 / 10 = 50%, 9.5 / 10 = 95%
    assert runs[0]["where"] == "start (5% into the flight)"
    assert runs[1]["where"] == "middle (50% into the flight)"
    assert runs[2]["where"] == "end (95% into the flight)"
    assert dropped_runs(np.array([], np.int64), 5) == []
    assert dropped_runs(np.arange(4), 4)[0]["where"] == "whole flight"


def test_pose_jumps_flag_a_frame_that_leaves_the_path_and_comes_back():
    # 7 frames 1 unit apart along x (median step 1); frame 3 pushed 6 units sideways: its steps
    # are sqrt(1 + 36) = 6.1 > 5 x median, its neighbours 2 and 4 are 2 apart (< 6.1 / 2)
    line = np.stack([np.arange(7.0), np.zeros(7), np.zeros(7)], axis=1)
    frames = np.array([0, 1, 2, 3, 4, 5, 6]) + 10  # indices are reported, not positions
    bent = line.copy()
    bent[3, 1] = 6.0
    assert pose_jumps(bent, frames) == [13]
    assert pose_jumps(line, frames) == []
    # a real long step (the flight moves on and does not come back) is no jump
    far = line.copy()
    far[4:, 0] += 20.0
    assert pose_jumps(far, frames) == []
    # the first and last frames have one neighbour only: never judged
    ends = line.copy()
    ends[0, 1] = ends[6, 1] = 50.0
    assert pose_jumps(ends, frames) == []
    assert pose_jumps(line[:2], frames[:2]) == []


def test_drop_reason():
    assert drop_reason(3, 0, 16).startswith("textureless")
    assert drop_reason(300, 0, 16) == "no verified match with any other frame"
    assert "2 frame(s)" in drop_reason(300, 2, 16)


def test_format_report_mentions_the_essentials():
    report = {
        "status": "failed",
        "registered": 3,
        "frames_total": 10,
        "registration_rate": 0.3,
        "message": "only 30.0% registered",
        "dropped": [{"reason": "textureless (0 keypoints)"}] * 7,
        "dropped_runs": dropped_runs(np.arange(3, 10), 10),
        "accuracy": {"error": "alignment impossible: collinear"},
        "times": {"extract": 1.0},
    }
    text = format_report(report)
    assert "3/10 frames registered (30.0%)" in text
    assert "dropped frames 3-9 (7) at the end" in text
    assert "textureless: 7" in text
    assert "collinear" in text


def test_format_report_says_which_start_the_kept_model_has():
    """The initial pair line names the pair that started our model, how many others were tried,
    and says so when the kept model came from COLMAP's own initial pair instead."""
    pair = {"frames": ["00031.png", "00050.png"], "inliers": 117, "tri_angle_deg": 5.2}
    base = {"status": "ok", "registered": 102, "frames_total": 102, "registration_rate": 1.0}
    ours = {"chosen": pair, "tried": [{**pair, "model_frames": 102}], "kept": True}
    text = format_report({**base, "init_pair": ours})
    assert "initial pair 00031.png + 00050.png: 117 inliers" in text
    assert "tried" not in text and "COLMAP's own" not in text
    refused = {**pair, "model_frames": 0}
    theirs = {"chosen": refused, "tried": [refused, refused], "kept": False}
    text = format_report({**base, "init_pair": theirs})
    assert "(1 other pair(s) of ours tried)" in text
    assert "the kept model started from COLMAP's own initial pair instead" in text
