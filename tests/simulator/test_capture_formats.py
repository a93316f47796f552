"""The simulated Wi-Fi link (dropped, duplicated, torn frames), the drone capture folders and
their onboard telemetry: every defect present where flight.json says, absent when off."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dronecap.cli import main
from dronecap.simulator.sensor import Sensor, jpeg_roundtrip
from dronecap.simulator.simulate import Capture, SimulatedFlight
from dronecap.simulator.stream import LinkDefects, plan_stream, tear
from dronecap.simulator.telemetry import (
    BODY_FROM_CAMERA,
    StateNoise,
    body_poses,
    estimate,
    state_times,
)

LOSSY = ["--drop", "0.1", "--duplicate", "0.08", "--torn", "0.08"]


def test_link_plan_rates_and_bursts():
    plan = plan_stream(6000, LinkDefects(0.05, 0.03, 0.03), 160, seed=1)
    got = np.array([d.source for d in plan])
    assert got[0] == 0 and got[-1] == 5999 and np.all(np.diff(got) > 0)
    lost = 6000 - len(plan)
    assert 0.035 < lost / 6000 < 0.065
    gaps = np.diff(got)[np.diff(got) > 1] - 1
    assert gaps.mean() > 1.4  # losses come in bursts, not single frames
    dup = sum(d.shows != d.source for d in plan)
    torn = sum(d.tear_row is not None and d.shows == d.source for d in plan)
    assert 0.02 < dup / len(plan) < 0.04 and 0.02 < torn / len(plan) < 0.04
    clean = plan_stream(500, LinkDefects(), 160, seed=1)
    assert [(d.source, d.shows, d.tear_row) for d in clean] == [(s, s, None) for s in range(500)]


def test_tears_black_gray_and_shifted():
    img = np.arange(12 * 10, dtype=np.uint8).reshape(12, 10)
    np.testing.assert_array_equal(tear(img, 7, "black", 0)[7:], 0)
    np.testing.assert_array_equal(tear(img, 7, "gray", 0)[7:], 128)
    sh = tear(img, 7, "shifted", 13)  # 13 bytes lost: row 7 continues with byte 70 + 13
    np.testing.assert_array_equal(sh[:7], img[:7])
    assert sh[7, 0] == 83 and sh[8, 6] == 99
    np.testing.assert_array_equal(sh.reshape(-1)[-13:], 0)


@pytest.fixture(scope="module")
def nanocockpit(tmp_path_factory):
    """A 40-frame lossy NanoCockpit capture written by the CLI."""
    out = tmp_path_factory.mktemp("nc") / "capture"
    args = ["simulate", "--frames", "40", "--seed", "4", "--format", "nanocockpit", *LOSSY]
    assert main([*args, "-o", str(out)]) == 0
    return out, json.loads((out / "flight.json").read_text())


def test_nanocockpit_files_and_frame_ids(nanocockpit):
    out, gt = nanocockpit
    rows = list(csv.DictReader(open(out / "metadata.csv")))
    assert list(rows[0]) == [
        "filename", "frame_id", "frame_timestamp", "state_timestamp",
        "x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw",
    ]  # fmt: skip
    stream = gt["stream"]
    assert stream["dropped"] and stream["duplicated"] and stream["torn"]
    assert len(rows) == stream["delivered"] == len(gt["frames"]) == 40 - len(stream["dropped"])
    assert sorted(p.name for p in (out / "camera_raw").iterdir()) == [
        f"{k:05d}.png" for k in range(len(rows))
    ]
    ids = [int(r["frame_id"]) for r in rows]
    missing = sorted(set(range(40)) - set(ids))  # 40 frames: no wrap
    assert missing == stream["dropped"]
    for r, f in zip(rows, gt["frames"], strict=True):
        assert r["filename"] == f["file"] and int(r["frame_id"]) == f["source_frame"] % 256
        t = int(r["frame_timestamp"])
        assert t - int(r["state_timestamp"]) in range(0, 11_000)  # latest state, 100 Hz
        assert t == 2_000_000 + round(f["source_frame"] / 30 * 1e6)
    frames = [cv2.imread(str(out / f["file"]), cv2.IMREAD_UNCHANGED) for f in gt["frames"]]
    assert frames[0].shape == (160, 160) and frames[0].dtype == np.uint8
    for k, f in enumerate(gt["frames"]):
        if "shows" in f:  # the previous buffer again, byte for byte, with its pose
            np.testing.assert_array_equal(frames[k], frames[k - 1])
            assert f["c2w"] == gt["frames"][k - 1]["c2w"]
        elif "tear" in f:
            row, kind = f["tear"]["row"], f["tear"]["kind"]
            below = frames[k][row:]
            if kind == "black":
                assert below.max() == 0
            elif kind == "gray":
                assert (below == 128).all()
            else:
                assert below.reshape(-1)[-f["tear"]["shift"] :].max() == 0
            assert frames[k][:row].std() > 10  # the top part is the scene


def test_frame_id_wraps_at_256():
    sim = SimulatedFlight("corridor", 600, 0, Capture(link=LinkDefects(drop=0.05)))
    recs = sim.document("nanocockpit")["frames"]
    ids = [r["frame_id"] for r in recs]
    assert max(ids) == 255 and ids.count(0) >= 2  # counted around more than once
    steps = (np.diff(ids) % 256).tolist()
    assert sum(s - 1 for s in steps) == len(sim.document()["stream"]["dropped"])


def test_pulp_dronet_folder_and_state_rate(tmp_path):
    out = tmp_path / "pd"
    assert main(["simulate", "--frames", "30", "--format", "pulp-dronet", "-o", str(out)]) == 0
    gt = json.loads((out / "flight.json").read_text())
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == sorted(f"{2_000_000 + round(s / 30 * 1e6)}.jpeg" for s in range(30))
    img = cv2.imread(str(out / "images" / names[3]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (160, 160)
    rows = list(csv.reader(open(out / "state.csv")))
    assert rows[0] == [
        "timeTicks", "stateEstimate.x", "stateEstimate.y", "stateEstimate.z",
        "stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw",
    ]  # fmt: skip
    t = np.array([int(r[0]) for r in rows[1:]])
    dt = np.diff(t)
    assert (dt > 0).all() and np.median(dt) == pytest.approx(10_000, abs=300)
    assert 100 < np.std(dt) < 800  # jittered (300 us per stamp -> ~420 us per difference)
    frame_t = np.array([int(n.split(".")[0]) for n in names])
    nearest = np.abs(frame_t[:, None] - t[None]).min(1)
    assert nearest.max() < 6_000  # every frame has a state row within 20 ms
    assert len(gt["frames"]) == 30 and gt["telemetry"]["file"] == "state.csv"


def test_state_estimate_noise_scale_and_body_axes():
    """Noise statistics match the model; the scale error scales the horizontal track; the body
    attitude composed with the camera mount gives back the camera's rotation."""
    sim = SimulatedFlight("corridor", 300, 2, Capture())
    times = state_times(0.0, 9.9, StateNoise(), 2)
    c2w = sim.pose_at(times)
    body = body_poses(c2w)
    vel = np.zeros((len(times), 3))
    pure = StateNoise(5.0, 0.5, 20.0, scale=0.0, yaw_drift_deg_min=0.0, walk_mm_sqrt_s=0.0)
    est = estimate(times, body, vel, pure, 2)
    err = (est["position"] - body[:, :3, 3]) * 1e3
    assert np.std(err, axis=0) == pytest.approx([5.0] * 3, rel=0.15)
    att = Rotation.from_quat(est["quaternion"]).as_matrix()
    rel = Rotation.from_matrix(np.einsum("sji,sjk->sik", body[:, :3, :3], att))
    per_axis = np.degrees(rel.as_rotvec()).std(0)
    assert per_axis == pytest.approx([0.5] * 3, rel=0.15)
    np.testing.assert_allclose(att @ BODY_FROM_CAMERA, c2w[:, :3, :3], atol=np.radians(3))
    # camera looks along body +x
    np.testing.assert_allclose(body[:, :3, 0], c2w[:, :3, 2], atol=1e-12)
    only_scale = StateNoise(0, 0, 0, scale=0.01, yaw_drift_deg_min=0, walk_mm_sqrt_s=0)
    est = estimate(times, body, vel, only_scale, 2)
    d_true = body[-1, :3, 3] - body[0, :3, 3]
    d_est = est["position"][-1] - est["position"][0]
    np.testing.assert_allclose(d_est[:2], 1.01 * d_true[:2], atol=1e-9)
    assert d_est[2] == pytest.approx(d_true[2], abs=1e-9)  # height from the ToF sensor
    drift = StateNoise(0, 0, 0, scale=0, yaw_drift_deg_min=2.0, walk_mm_sqrt_s=0)
    est = estimate(times, body, vel, drift, 2)
    r_est = Rotation.from_quat(est["quaternion"][-1]).as_matrix()
    yaw = Rotation.from_matrix(body[-1, :3, :3].T @ r_est)
    expected = 2.0 * (times[-1] - times[0]) / 60
    assert np.degrees(np.linalg.norm(yaw.as_rotvec())) == pytest.approx(expected, abs=1e-6)


def test_clean_stream_is_complete_and_ground_truth_exact(tmp_path):
    assert main(["simulate", "--frames", "12", "--format", "nanocockpit", "-o",
                 str(tmp_path / "c")]) == 0  # fmt: skip
    gt = json.loads((tmp_path / "c" / "flight.json").read_text())
    assert gt["stream"]["dropped"] == gt["stream"]["duplicated"] == gt["stream"]["torn"] == []
    sim = SimulatedFlight("corridor", 12, 0, Capture())
    for k, f in enumerate(gt["frames"]):
        assert f["source_frame"] == k and "shows" not in f and "tear" not in f
        np.testing.assert_array_equal(f["c2w"], sim.poses[k])


@pytest.mark.parametrize(
    "args",
    [
        ["--seed", "-1"],
        ["--frames", "1"],
        ["--jpeg", "0"],
        ["--jpeg", "55.5"],
        ["--drop", "0.9"],
        ["--torn", "nan"],
        ["--distortion", "abc"],
        ["--distortion", "-0.1"],
        ["--distortion", "-0.1,-2"],
        ["--noise", "-1,0.3"],
        ["--vignetting", "1.5"],
        ["--blur", "50"],
        ["--size", "0x0"],
        ["--focal", "-3"],
        ["--principal-offset", "0.9,0"],
        ["--state-noise", "5,0.5"],
        ["--exposure-drift", "1.2"],
    ],
)
def test_bad_values_one_line_nothing_written(tmp_path, capsys, args):
    assert main(["simulate", "--frames", "3", *args, "--workdir", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_pulp_dronet_jpeg_is_encoded_once_at_the_file(tmp_path):
    out = tmp_path / "pd"
    args = ["simulate", "--frames", "4", "--format", "pulp-dronet", "--jpeg", "60"]
    assert main([*args, "--noise", "3,0.3", "-o", str(out)]) == 0
    gt = json.loads((out / "flight.json").read_text())
    assert gt["sensor"]["jpeg_quality"] == 60
    raw = Capture(Sensor(read_noise=3.0, shot_noise=0.3))
    frame = SimulatedFlight("corridor", 4, 0, raw).render_source(2)
    got = cv2.imread(str(out / gt["frames"][2]["file"]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got, jpeg_roundtrip(frame, 60))


@pytest.mark.parametrize("fmt", ["mp4", "nanocockpit"])
def test_output_of_the_wrong_kind_one_line(tmp_path, capsys, fmt):
    target = tmp_path / "out.mp4"
    target.mkdir() if fmt == "mp4" else target.write_text("x")
    assert main(["simulate", "--frames", "3", "--format", fmt, "-o", str(target)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(target) in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mp4"]
