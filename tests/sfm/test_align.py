"""Umeyama alignment and pose-accuracy maths on hand-made transforms and degenerate layouts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dronecap.errors import InputError
from dronecap.sfm.align import (
    DegenerateAlignment,
    accuracy_against,
    load_ground_truth,
    pose_accuracy,
    rotation_angle_deg,
    step_rotation_errors_deg,
    umeyama,
)


def rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def poses_at(centres: np.ndarray, rots: np.ndarray | None = None) -> np.ndarray:
    out = np.tile(np.eye(4), (len(centres), 1, 1))
    out[:, :3, 3] = centres
    if rots is not None:
        out[:, :3, :3] = rots
    return out


SQUARE_ISH = np.array([[0, 0, 0], [1, 0, 0], [1, 2, 0], [0, 2, 0.5], [0.5, 1, 1.0]], float)


def test_umeyama_recovers_a_hand_made_similarity():
    # target = 2 * Rz(90) @ x + (1, 2, 3): e.g. (1, 0, 0) -> 2 * (0, 1, 0) + t = (1, 4, 3)
    target = 2.0 * SQUARE_ISH @ rot_z(90).T + np.array([1.0, 2.0, 3.0])
    assert np.allclose(target[1], [1.0, 4.0, 3.0])
    sim = umeyama(SQUARE_ISH, target)
    assert sim.scale == pytest.approx(2.0)
    assert np.allclose(sim.rotation, rot_z(90), atol=1e-12)
    assert np.allclose(sim.translation, [1, 2, 3])
    assert np.allclose(sim.apply_points(SQUARE_ISH), target)


def test_umeyama_never_returns_a_reflection():
    mirrored = SQUARE_ISH * np.array([1.0, 1.0, -1.0])  # a mirror image: no rotation fits exactly
    sim = umeyama(SQUARE_ISH, mirrored)
    assert np.linalg.det(sim.rotation) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("points", "words"),
    [
        (np.zeros((5, 3)) + 3.0, "coincide"),  # hovering drone: no baseline
        (np.outer(np.arange(6.0), [1.0, 2.0, 0.5]), "collinear"),  # straight line
        (np.outer(np.arange(6.0), [1.0, 0, 0]) + 1e-7 * np.eye(6, 3), "collinear"),  # jitter
        (SQUARE_ISH[:2], "at least 3"),
    ],
)
def test_umeyama_refuses_degenerate_centres(points, words):
    with pytest.raises(DegenerateAlignment, match=words):
        umeyama(points, points + 1.0)


def test_pose_accuracy_of_an_exact_similarity_is_zero():
    gt = poses_at(SQUARE_ISH * 3.0, np.stack([rot_z(10 * i) for i in range(5)]))
    # estimated frame: gt seen through an unknown similarity (scale 0.5, Rx(30), shift)
    s, r, t = 0.5, rot_x(30), np.array([0.1, -2.0, 5.0])
    est = gt.copy()
    est[:, :3, :3] = r @ gt[:, :3, :3]
    est[:, :3, 3] = s * gt[:, :3, 3] @ r.T + t
    acc = pose_accuracy(est, gt, total_gt=10)
    assert acc.ate_rmse == pytest.approx(0.0, abs=1e-9)
    assert acc.rot_max_deg == pytest.approx(0.0, abs=1e-5)
    assert acc.scale == pytest.approx(2.0)
    assert acc.registration_rate == pytest.approx(0.5)  # 5 of 10
    # extent: box of 3 * SQUARE_ISH is 3 x 6 x 3 -> diagonal sqrt(9 + 36 + 9)
    assert acc.extent == pytest.approx(np.sqrt(54.0))


def test_pose_accuracy_reports_a_rotated_camera_and_a_shifted_centre():
    centres = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    gt = poses_at(centres)
    est = gt.copy()
    est[2, :3, :3] = rot_z(5.0)  # one camera turned by 5 degrees; centres untouched
    acc = pose_accuracy(est, gt)
    assert acc.rot_max_deg == pytest.approx(5.0)
    assert acc.rot_median_deg == pytest.approx(0.0, abs=1e-6)
    assert acc.ate_rmse == pytest.approx(0.0, abs=1e-9)
    # lift one centre by 0.4 out of the plane: the best similarity spreads the error, RMSE > 0
    est[2, 2, 3] = 0.4
    acc = pose_accuracy(est, gt)
    assert 0.0 < acc.ate_rmse < 0.4 / 2 + 1e-9
    assert acc.ate_percent == pytest.approx(100 * acc.ate_rmse / np.sqrt(32.0))


def test_pose_accuracy_warns_when_errors_rival_the_sideways_spread():
    # a long thin flight: 10 m along x, +-0.05 m sideways (RMS sideways spread 0.05 / sqrt(2))
    n = 20
    centres = np.column_stack([np.linspace(0, 10, n), 0.05 * (-1.0) ** np.arange(n), np.zeros(n)])
    centres[::3, 2] += 0.04
    gt = poses_at(centres)
    assert pose_accuracy(gt, gt).warning == ""
    noisy = gt.copy()
    noisy[:, :3, 3] += 0.1 * np.random.default_rng(1).normal(size=(n, 3))  # errors ~0.1 m
    acc = pose_accuracy(noisy, gt)
    assert "weakly determined" in acc.warning


def test_step_rotation_errors_need_no_alignment():
    """Every view turned by the same 40 deg world rotation, the centres left (what a wrong
    alignment rotation does to the views): the aligned rotation errors are 40 deg, the
    consecutive-frame errors 0 (the model's shape is right)."""
    gt = poses_at(SQUARE_ISH, np.stack([rot_z(10.0 * k) for k in range(len(SQUARE_ISH))]))
    turned = gt.copy()
    turned[:, :3, :3] = rot_x(40.0) @ gt[:, :3, :3]
    acc = pose_accuracy(turned, gt)
    assert acc.rot_median_deg == pytest.approx(40.0, abs=1e-6)
    assert acc.step_rot_max_deg == pytest.approx(0.0, abs=1e-4)


def test_a_bent_model_is_told_apart_from_a_weak_alignment():
    """A corridor-like flight whose second half the model bends by 30 deg (centres and views,
    as a wrong start gives): the errors rival the sideways spread, and the warning says that
    the consecutive-frame rotations, which need no alignment, are off by the bend."""
    n = 20
    centres = np.column_stack(
        [np.linspace(0, 10, n), 0.3 * np.sin(np.arange(n)), 0.2 * np.cos(np.arange(n) / 2)]
    )
    gt = poses_at(centres)
    bent = gt.copy()
    half = n // 2
    bent[half:, :3, 3] = (centres[half:] - centres[half]) @ rot_z(30.0).T + centres[half]
    bent[half:, :3, :3] = rot_z(30.0) @ gt[half:, :3, :3]
    steps = step_rotation_errors_deg(bent, gt)
    assert steps.shape == (n - 1,)
    assert steps[half - 1] == pytest.approx(30.0, abs=1e-6)  # the step across the bend
    assert np.delete(steps, half - 1).max() == pytest.approx(0.0, abs=1e-4)
    acc = pose_accuracy(bent, gt)
    assert acc.step_rot_max_deg == pytest.approx(30.0, abs=1e-6)
    assert "weakly determined" in acc.warning and "reach 30 deg" in acc.warning


def test_rotation_angle_deg_by_hand():
    assert rotation_angle_deg(np.stack([np.eye(3), rot_z(30), rot_x(-120)])) == pytest.approx(
        [0.0, 30.0, 120.0]
    )


def test_accuracy_against_matches_by_source_index_and_flags_degenerate():
    gt = {10 * i: m for i, m in enumerate(poses_at(SQUARE_ISH))}
    est = poses_at(SQUARE_ISH[[0, 2, 3, 4]])
    acc = accuracy_against(est, np.array([0, 20, 30, 40]), gt, np.array([0, 10, 20, 30, 40, 99]))
    assert acc["matched"] == 4 and acc["total_gt"] == 5  # frame 99 has no ground truth
    assert acc["ate_rmse"] == pytest.approx(0.0, abs=1e-9)
    line = poses_at(np.outer(np.arange(3.0), [1, 0, 0]))
    bad = accuracy_against(line, np.array([0, 10, 20]), gt, np.array([0, 10, 20]))
    assert "collinear" in bad["error"]
    assert "error" in accuracy_against(est, np.array([1, 2, 3, 4]), gt, np.array([1, 2, 3, 4]))


def test_load_ground_truth(tmp_path):
    good = tmp_path / "poses.json"
    good.write_text(json.dumps({"fps": 30, "frames": [{"index": 7, "c2w": np.eye(4).tolist()}]}))
    assert list(load_ground_truth(good)) == [7]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"frames": [{"index": 1}]}))
    with pytest.raises(InputError, match="frames"):
        load_ground_truth(bad)
    with pytest.raises(InputError, match="not found"):
        load_ground_truth(tmp_path / "missing.json")


def test_tum_ground_truth_is_matched_by_nearest_timestamp(tmp_path):
    from dronecap.datasets.trajectory import write_tum

    times = np.array([0.0, 0.1, 0.2, 0.3])
    poses = poses_at(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], float))
    path = write_tum(tmp_path / "gt.txt", times, poses)
    # frames at 0.105 s (5 ms from pose 1), 0.21 s (10 ms from pose 2), 0.25 s (50 ms: none)
    gt = load_ground_truth(path, np.array([7, 8, 9]), np.array([0.105, 0.21, 0.25]))
    assert sorted(gt) == [7, 8]
    assert np.allclose(gt[7][:3, 3], [1, 0, 0]) and np.allclose(gt[8][:3, 3], [2, 0, 0])
    with pytest.raises(InputError, match="within 20 ms"):
        load_ground_truth(path, np.array([0]), np.array([5.0]))
