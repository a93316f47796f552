"""The SfM report: what registered, what was dropped and where in the flight, quality, timing.

The report is a JSON-able dict (stored as ``sfm/report.json``); :func:`format_report` renders
it for the terminal. docs/sfm.md explains each field.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from dronecap.sfm.drones import drone_lines

ADVICE = (
    "try: more sequential overlap (--overlap 20) or --matcher exhaustive; keep more frames at "
    "ingest (fewer dropped, less motion between frames); give known intrinsics in frames.h5; "
    "more features (--max-features 4096) or finer SIFT scales (--first-octave -2)"
)


def drop_reason(keypoints: int, partners: int, min_keypoints: int) -> str:
    """Why a frame is missing from the model, from its keypoint and verified-partner counts."""
    if keypoints < min_keypoints:
        return f"textureless ({keypoints} keypoints)"
    if partners == 0:
        return "no verified match with any other frame"
    return f"matched with {partners} frame(s) but could not be registered"


def dropped_runs(dropped: np.ndarray, n: int) -> list[dict[str, Any]]:
    """Group dropped frame indices into consecutive runs and place each in the flight.

    Args:
        dropped: int [D] sorted indices (0..n-1) of frames missing from the model.
        n: number of frames in the flight.

    Returns:
        one dict per run: first, last, count, and "where" (start / middle / end of the flight,
        with the run's position as a percentage of the flight).
    """
    runs: list[dict[str, Any]] = []
    for i in np.asarray(dropped, dtype=np.int64):
        if runs and i == runs[-1]["last"] + 1:
            runs[-1]["last"] = int(i)
            runs[-1]["count"] += 1
        else:
            runs.append({"first": int(i), "last": int(i), "count": 1})
    for r in runs:
        mid = 100.0 * (r["first"] + r["last"]) / 2 / max(n - 1, 1)
        if r["count"] == n:
            r["where"] = "whole flight"
            continue
        place = "start" if r["first"] == 0 else "end" if r["last"] == n - 1 else "middle"
        r["where"] = f"{place} ({mid:.0f}% into the flight)"
    return runs


JUMP_FACTOR = 5.0  # a frame this many median steps away from both flight neighbours is a jump


def pose_jumps(
    centres: np.ndarray, frames: np.ndarray, flights: np.ndarray | None = None
) -> list[int]:
    """Registered frames whose camera leaves the path of its neighbours and comes back.

    Args:
        centres: float [R, 3] camera centres of the registered frames, in flight order.
        frames: int [R] their frame indices.
        flights: int [R] the drone of each frame (a swarm: each flight is checked on its own,
            in frame order within it); None: one flight.

    Returns:
        frame indices k whose distance to both the previous and the next registered frame exceeds
        :data:`JUMP_FACTOR` times the median step while those two neighbours lie within half
        that distance of each other. Such a pose fits its points but not the flight (seen on
        Himax test_15: one frame 3 units sideways and 15 deg rotated between neighbours 0.7
        units apart, a rotation-translation ambiguity of a forward view of distant points).
    """
    if flights is not None and len(np.unique(flights)) > 1:
        return sorted(
            j
            for d in np.unique(flights)
            for j in pose_jumps(np.asarray(centres)[flights == d], np.asarray(frames)[flights == d])
        )
    c = np.asarray(centres, dtype=np.float64)
    if len(c) < 3:
        return []
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)  # [R - 1]
    med = float(np.median(step))
    if med <= 0.0:
        return []
    away = np.minimum(step[:-1], step[1:])  # [R - 2], frames 1..R-2
    across = np.linalg.norm(c[2:] - c[:-2], axis=1)
    jump = (away > JUMP_FACTOR * med) & (across < 0.5 * away)
    return [int(f) for f in np.asarray(frames)[1:-1][jump]]


def _initial_pair_lines(info: dict[str, Any]) -> list[str]:
    """Report lines on our initial pair: which one started the model, or why none did."""
    init = info.get("chosen")
    if not init:
        return []
    tried = len(info.get("tried", [])) - 1
    line = (
        f"  initial pair {init['frames'][0]} + {init['frames'][1]}: {init['inliers']} inliers, "
        f"triangulation angle {init['tri_angle_deg']:.1f} deg"
    )
    if tried > 0:
        line += f" ({tried} other pair(s) of ours tried)"
    if info.get("kept") is False:
        line += "; the kept model started from COLMAP's own initial pair instead"
    return [line]


def format_report(report: dict[str, Any]) -> str:
    """Human-readable multi-line summary of a report dict."""
    lines = [
        f"sfm {report['status']}: {report['registered']}/{report['frames_total']} frames registered"
        f" ({100 * report['registration_rate']:.1f}%)"
    ]
    if report.get("message"):
        lines.append(f"  {report['message']}")
    lines += _quality_lines(report.get("quality") or {})
    lines += _bend_lines(report.get("bend_check") or {})
    lines += _camera_lines(report.get("camera") or {})
    lines += drone_lines(report)
    lines += _initial_pair_lines(report.get("init_pair") or {})
    kf = report.get("keyframes")
    if kf and kf["keyframes"] < kf["frames"]:
        lines.append(
            f"  keyframes: {kf['keyframes']} of {kf['frames']} frames mapped (up to "
            f"{kf['flow_px']:g} px apart), the others registered into their model"
        )
    attempts = report.get("attempts") or []
    if len(attempts) > 1:
        tried = "; ".join(
            f"{' + '.join(a['remedies']) or 'first'}: {a['registered']} frames" for a in attempts
        )
        lines.append(f"  attempts: {tried}; kept: {report.get('remedy') or 'the first'}")
    lines += _prior_lines(report.get("priors") or {})
    models = report.get("models")
    if models:
        found = ", ".join(f"{k} {v['frames']} ({v['reproj']:.2f} px)" for k, v in models.items())
        lines.append(f"  models (frames, reprojection error): {found}")
        lines.append(f"  kept: {report.get('chosen_model')}")
    lines += _dropped_lines(report)
    lines += _accuracy_lines(report.get("accuracy") or {})
    t = report.get("times", {})
    if t:
        lines.append("  time: " + ", ".join(f"{k} {v:.1f}s" for k, v in t.items()))
    return "\n".join(lines)


def _quality_lines(q: dict[str, Any]) -> list[str]:
    """Report lines on the model's points and pose jumps."""
    if not q:
        return []
    lines = [
        f"  points {q['points']} ({q['points_kept']} kept for bounds), mean track length "
        f"{q['mean_track_length']:.2f}, mean reprojection error "
        f"{q['mean_reprojection_error_px']:.3f} px"
    ]
    if q.get("pose_jumps"):
        lines.append(
            f"  pose jumps: frame(s) {', '.join(map(str, q['pose_jumps']))} lie more than "
            f"{JUMP_FACTOR:g} median steps off the path of their neighbours (check them)"
        )
    return lines


def _camera_lines(cam: dict[str, Any]) -> list[str]:
    """The report line on the camera used (a swarm's first drone; the others in drone_lines)."""
    if not cam:
        return []
    dist = f" distortion {cam['distortion']}" if cam["distortion"] else ""
    how = cam.get("mode", "fixed" if cam["fixed"] else "estimated")
    src = f", from {cam['source']}" if cam.get("source", "none") != "none" else ""
    return [
        f"  camera {cam['model']} ({how}{src}) fx={cam['fx']:.2f} fy={cam['fy']:.2f} "
        f"cx={cam['cx']:.2f} cy={cam['cy']:.2f}{dist}"
    ]


def _prior_lines(pri: dict[str, Any]) -> list[str]:
    """Report lines on the telemetry priors' fit."""
    if not pri:
        return []
    if "error" in pri:
        return [f"  priors: {pri['error']}"]
    if "position_median_m" not in pri:  # a swarm whose drones' frames differ
        return [
            f"  priors: metres and z up from {pri['used']} frames ({pri['method']}: the drones' "
            f"telemetry has no common frame), {pri['scale_m_per_unit']:.4g} m per SfM unit"
        ]
    lines = [
        f"  priors: metres and z up from {pri['used']} frames ({pri['method']}), "
        f"{pri['scale_m_per_unit']:.4g} m per SfM unit; recovered vs prior: position "
        f"{pri['position_median_m']:.3f} m median, rotation "
        f"{pri['rotation_median_deg']:.2f} deg median"
    ]
    if pri.get("fallback_frames"):
        lines.append(f"  {len(pri['fallback_frames'])} unregistered frame(s) kept with their prior")
    return lines


def _dropped_lines(report: dict[str, Any]) -> list[str]:
    """Report lines on the frames that did not register: where, and why."""
    lines = []
    for r in report.get("dropped_runs", [])[:10]:
        span = f"{r['first']}" if r["count"] == 1 else f"{r['first']}-{r['last']}"
        lines.append(f"  dropped frames {span} ({r['count']}) at the {r['where']}")
    reasons: dict[str, int] = {}
    for d in report.get("dropped", []):
        key = re.sub(r"\d+", "K", d["reason"].split(" (")[0])
        reasons[key] = reasons.get(key, 0) + 1
    if reasons:
        lines.append("  why: " + ", ".join(f"{k}: {v}" for k, v in reasons.items()))
    return lines


def _accuracy_lines(acc: dict[str, Any]) -> list[str]:
    """Report lines on the accuracy against ground truth."""
    if not acc:
        return []
    if "error" in acc:
        return [f"  accuracy: {acc['error']}"]
    lines = [
        f"  vs ground truth: ATE {acc['ate_rmse']:.4f} ({acc['ate_percent']:.2f}% of extent "
        f"{acc['extent']:.3f}), rotation error median {acc['rot_median_deg']:.3f} deg, max "
        f"{acc['rot_max_deg']:.3f} deg, registered {100 * acc['registration_rate']:.1f}%",
        f"  consecutive-frame rotation error (no alignment): median "
        f"{acc['step_rot_median_deg']:.3f} deg, max {acc['step_rot_max_deg']:.3f} deg",
    ]
    if acc.get("warning"):
        lines.append(f"  warning: {acc['warning']}")
    return lines


def _bend_lines(bend: dict[str, Any]) -> list[str]:
    """The report's line on the bent-model check (:mod:`dronecap.sfm.bend`), if it ran."""
    if not bend.get("pairs"):
        return []
    verdict = "BENT, do not trust these poses" if bend["bent"] else "straight"
    return [
        f"  bend check (model vs two-view rotations of {bend['pairs']} consecutive pairs): "
        f"median {bend['median_deg']:.2f}, p95 {bend['p95_deg']:.2f}, max {bend['max_deg']:.2f} "
        f"deg: {verdict}"
    ]
