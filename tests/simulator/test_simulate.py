"""The flight simulator: determinism, the ground-truth file, and GT poses that match the video."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from dronecap.cli import main
from dronecap.datasets import open_dataset
from dronecap.simulator.flights import camera_to_world
from dronecap.simulator.simulate import render_flight


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 40-frame corridor flight rendered through the CLI (video, GT JSON, decoded frames)."""
    work = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--frames", "40", "--seed", "3", "--workdir", str(work)]) == 0
    gt = json.loads((work / "flight.json").read_text())
    cap = cv2.VideoCapture(str(work / "flight.mp4"))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    return work, gt, frames


def test_ground_truth_file_format(flight):
    _, gt, frames = flight
    assert gt["fps"] == 30
    assert set(gt["intrinsics"]) == {"fx", "fy", "cx", "cy", "width", "height"}
    assert len(gt["frames"]) == len(frames) == 40
    for i, f in enumerate(gt["frames"]):
        assert f["index"] == i and f["timestamp"] == pytest.approx(i / 30)
        c2w = np.array(f["c2w"])
        assert c2w.shape == (4, 4)
        r = c2w[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0)
    assert len(gt["scene"]["cones"]) == 2


def test_same_seed_same_video_other_seed_differs():
    a, _ = render_flight("corridor", 100, seed=7)
    b, _ = render_flight("corridor", 100, seed=7)
    c, _ = render_flight("corridor", 100, seed=8)
    fa, fb, fc = next(a), next(b), next(c)
    np.testing.assert_array_equal(fa, fb)
    assert np.abs(fa.astype(int) - fc).mean() > 5


def floor_warp_error(frames, gt, i: int, j: int, pose_j: np.ndarray) -> float:
    """Median |I_i - I_j(warped)| (DN) over floor pixels of frame i, mapping each floor pixel of
    view i to view j through the plane z = 0 with the GT poses and intrinsics."""
    k = gt["intrinsics"]
    kmat = np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1.0]])
    ci = np.array(gt["frames"][i]["c2w"])
    v, u = np.mgrid[0:160, 0:160].astype(float)
    rays = np.stack([u + 0.5, v + 0.5, np.ones_like(u)], -1) @ np.linalg.inv(kmat).T
    d = rays @ ci[:3, :3].T
    o = ci[:3, 3]
    t = -o[2] / np.where(d[..., 2] < -1e-6, d[..., 2], np.nan)
    x = o + d * t[..., None]  # floor point seen by each pixel of view i
    (x0, y0, _), (x1, y1, _) = gt["scene"]["bounds"]
    keep = (x[..., 0] > x0 + 0.1) & (x[..., 0] < x1 - 0.1) & (np.abs(x[..., 1]) < y1 - 0.1)
    for cone in gt["scene"]["cones"]:  # cones stand on the floor: leave them out
        keep &= np.hypot(x[..., 0] - cone["position"][0], x[..., 1] - cone["position"][1]) > 0.6
    xc = (x - pose_j[:3, 3]) @ pose_j[:3, :3]  # world -> camera j
    pj = xc @ kmat.T
    uj, vj = pj[..., 0] / pj[..., 2] - 0.5, pj[..., 1] / pj[..., 2] - 0.5
    keep &= (uj > 1) & (uj < 158) & (vj > 1) & (vj < 158) & (xc[..., 2] > 0)
    warped = cv2.remap(
        frames[j].astype(np.float32),
        np.nan_to_num(uj).astype(np.float32),
        np.nan_to_num(vj).astype(np.float32),
        cv2.INTER_LINEAR,
    )
    assert keep.sum() > 1000, "too few floor pixels to compare"
    return float(np.median(np.abs(warped - frames[i])[keep]))


def test_gt_poses_and_intrinsics_explain_the_rendered_floor(flight):
    """Mapping the floor from frame i into frame i + 1 with the GT matches the video to sensor
    noise; the same with a wrong pose (frame i + 7's) does not."""
    _, gt, frames = flight
    for i in (5, 20):
        right = floor_warp_error(frames, gt, i, i + 1, np.array(gt["frames"][i + 1]["c2w"]))
        wrong = floor_warp_error(frames, gt, i, i + 1, np.array(gt["frames"][i + 7]["c2w"]))
        assert right < 4.5  # noise sigma ~2.5 DN at mid gray -> median |difference| ~3 DN
        assert wrong > 2 * right


def test_camera_axes_are_opencv():
    # yaw 0, pitch 0: looking along world +x; image right = world -y, image down = world -z.
    m = camera_to_world(np.zeros((1, 3)), np.zeros(1), np.zeros(1), np.zeros(1))[0]
    np.testing.assert_allclose(m[:3, 2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(m[:3, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(m[:3, 1], [0, 0, -1], atol=1e-12)


def test_ingest_of_a_simulated_flight_picks_up_its_intrinsics(flight, capsys):
    work, gt, _ = flight
    assert main(["ingest", str(work / "flight.mp4"), "--workdir", str(work)]) == 0
    assert "intrinsics from" in capsys.readouterr().out
    ds = open_dataset(work / "frames.h5")
    assert ds.intrinsics.fx == gt["intrinsics"]["fx"]
    assert set(ds.source_index) <= set(range(40))


def test_orbit_scene_renders():
    frames, gt = render_flight("orbit", 60, seed=0)
    f = next(frames)
    assert f.shape == (160, 160) and 40 < f.mean() < 200 and f.std() > 20
    assert gt["scene"]["name"] == "orbit"


def test_bad_simulate_options(tmp_path, capsys):
    assert main(["simulate", "--frames", "1", "--workdir", str(tmp_path)]) == 1
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (tmp_path / "flight.mp4").exists()
