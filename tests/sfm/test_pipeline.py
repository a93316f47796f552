"""`dronecap sfm` end to end on real pycolmap: lego views as a flight, and hard cases."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dronecap.cli import main as cli_main
from dronecap.datasets.format import Dataset, open_dataset, write_dataset
from dronecap.errors import InputError
from dronecap.files import sha256_file
from dronecap.sfm.blender_flight import blender_flight
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.pipeline import run_sfm


def write_flight(tmp_path, ds: Dataset, gt: dict | None = None):
    frames = tmp_path / "frames.h5"
    write_dataset(frames, ds)
    gt_path = None
    if gt is not None:
        gt_path = tmp_path / "poses.json"
        gt_path.write_text(json.dumps(gt))
    return frames, gt_path


def concat(a: Dataset, b: Dataset) -> Dataset:
    return Dataset(
        images=np.concatenate([a.images, b.images]),
        kind="frames",
        intrinsics=a.intrinsics,
        names=a.names + b.names,
        source_index=np.concatenate([a.source_index, b.source_index]),
        timestamps=np.concatenate([a.timestamps, b.timestamps]),
    )


def black(n: int, first_index: int) -> Dataset:
    idx = np.arange(first_index, first_index + n)
    return Dataset(
        images=np.zeros((n, 160, 160, 1), np.uint8),
        kind="frames",
        names=[f"black_{i}" for i in idx],
        source_index=idx,
        timestamps=idx / 30.0,
    )


@pytest.fixture(scope="module")
def lego_run(lego_dir, tmp_path_factory):
    """30 consecutive lego test views with two black frames in the middle, known intrinsics."""
    tmp = tmp_path_factory.mktemp("lego")
    ds, gt = blender_flight(lego_dir, count=30)
    first, second = ds.subset(np.arange(15)), ds.subset(np.arange(15, 30))
    flight = concat(concat(first, black(2, 1000)), second)
    flight.intrinsics = ds.intrinsics
    frames, gt_path = write_flight(tmp, flight, gt)
    opts = SfmOptions(matcher="sequential", overlap=5, loop_period=5, loop_num_images=5)
    report = run_sfm(frames, tmp / "posed.h5", tmp / "sfm", opts, gt_path, progress=False)
    return tmp, report, flight


def test_lego_sequence_registers_and_matches_ground_truth(lego_run):
    tmp, report, flight = lego_run
    assert report["status"] == "ok"
    assert report["matching"]["matcher"] == "sequential" and report["matching"]["loop_detection"]
    assert report["registered"] >= 29  # 30 textured frames; both black frames must drop
    acc = report["accuracy"]
    assert acc["total_gt"] == 30  # black frames have no ground truth
    assert acc["registration_rate"] >= 29 / 30
    assert acc["ate_percent"] < 2.0
    # a 30-frame arc pins the alignment rotation loosely (measured ~3 deg; 200 frames: ~1 deg)
    assert acc["rot_median_deg"] < 6.0
    assert 0 < report["quality"]["mean_reprojection_error_px"] < 1.5
    assert report["quality"]["mean_track_length"] > 2
    assert report["camera"]["fixed"]


def test_black_frames_are_reported_where_they_sit(lego_run):
    _, report, _ = lego_run
    black_drops = [d for d in report["dropped"] if d["name"].startswith("black")]
    assert [d["frame"] for d in black_drops] == [15, 16]
    assert all(d["reason"].startswith("textureless") for d in black_drops)
    run = next(r for r in report["dropped_runs"] if r["first"] == 15)
    assert run["last"] == 16 and run["where"].startswith("middle")


def test_posed_file_contract(lego_run):
    tmp, report, flight = lego_run
    posed = open_dataset(tmp / "posed.h5", kinds=("posed",))
    assert posed.n == report["registered"]
    assert not any(n.startswith("black") for n in posed.names)
    r = posed.poses[:, :3, :3]
    assert np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    # known PINHOLE intrinsics were kept fixed and stored unchanged (same pixel convention)
    k = posed.intrinsics
    assert (k.model, k.cx, k.cy) == ("PINHOLE", 80.0, 80.0)
    assert k.fx == pytest.approx(flight.intrinsics.fx)
    # normalised scene: cameras inside the AABB, upright on average, near < far
    lo, hi = posed.aabb
    assert np.all(posed.poses[:, :3, 3] > lo) and np.all(posed.poses[:, :3, 3] < hi)
    assert np.max(hi - lo) < 2.5
    up = -posed.poses[:, :3, 1].mean(0)
    assert up[2] / np.linalg.norm(up) > 0.99
    assert np.all(posed.near_far[:, 0] > 0) and np.all(posed.near_far[:, 1] > posed.near_far[:, 0])
    m = posed.normalization
    assert m.shape == (4, 4) and np.allclose(m[3], [0, 0, 0, 1])
    assert posed.provenance["inputs"]["frames.h5"] == sha256_file(tmp / "frames.h5")
    for name in ("model/cameras.bin", "model/images.bin", "model/points3D.bin", "points.ply"):
        assert (tmp / "sfm" / name).stat().st_size > 0
    assert json.loads((tmp / "sfm" / "report.json").read_text())["registered"] == posed.n


def test_two_disconnected_parts_keep_the_larger(lego_dir, tmp_path):
    """Frames 0-19 and 150-159 (the far side of the orbit): no shared view, unknown camera."""
    ds, _ = blender_flight(lego_dir)
    flight = ds.subset(np.r_[0:20, 150:160])
    flight.intrinsics = None
    frames, _ = write_flight(tmp_path, flight)
    opts = SfmOptions(matcher="exhaustive", retry_below=0.0)  # no retries: 2 parts by design
    report = run_sfm(frames, tmp_path / "posed.h5", tmp_path / "sfm", opts, progress=False)
    assert report["status"] == "ok"
    assert 18 <= report["registered"] <= 20
    # self-calibrated: mapped with one radial term, the final adjustment adds the second
    assert report["camera"]["model"] == "RADIAL" and not report["camera"]["fixed"]
    assert any(r["first"] == 20 and r["last"] == 29 for r in report["dropped_runs"])
    posed = open_dataset(tmp_path / "posed.h5")
    assert set(posed.source_index) <= set(range(20))


def test_black_flight_fails_with_a_report(tmp_path):
    frames, _ = write_flight(tmp_path, black(6, 0))
    code = cli_main(["sfm", "--workdir", str(tmp_path), "--quiet"])
    assert code == 1
    report = json.loads((tmp_path / "sfm" / "report.json").read_text())
    assert report["status"] == "failed" and "keypoints" in report["message"]
    assert len(report["dropped"]) == 6
    assert not (tmp_path / "posed.h5").exists()


def test_too_few_frames(tmp_path):
    frames, _ = write_flight(tmp_path, black(2, 0))
    with pytest.raises(InputError, match="at least 3"):
        run_sfm(frames, tmp_path / "posed.h5", tmp_path / "sfm", SfmOptions(), progress=False)


def test_pure_rotation_does_not_crash(lego_dir, tmp_path):
    """One viewpoint turned in place (homographies K R K^-1): no baseline to triangulate."""
    import cv2

    ds, _ = blender_flight(lego_dir, count=1)
    k = ds.intrinsics.matrix()
    frames = []
    for yaw in np.linspace(-6, 6, 12):
        a = np.radians(yaw)
        rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        h = k @ rot @ np.linalg.inv(k)
        # pixel centres at +0.5: conjugate the homography by that shift for OpenCV's warp
        shift = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
        h = np.linalg.inv(shift) @ h @ shift
        frames.append(cv2.warpPerspective(ds.images[0, ..., 0], h, (160, 160), borderValue=255))
    idx = np.arange(12)
    flight = Dataset(
        images=np.stack(frames)[..., None],
        kind="frames",
        intrinsics=ds.intrinsics,
        source_index=idx,
        timestamps=idx / 30.0,
    )
    path, _ = write_flight(tmp_path, flight)
    with pytest.raises(InputError, match="no baseline"):
        run_sfm(path, tmp_path / "posed.h5", tmp_path / "sfm", SfmOptions(), progress=False)
    report = json.loads((tmp_path / "sfm" / "report.json").read_text())
    assert report["status"] == "failed" and report["registered"] == 0
    whole = {"first": 0, "last": 11, "count": 12, "where": "whole flight"}
    assert report["dropped_runs"] == [whole]
    assert not (tmp_path / "posed.h5").exists()


@pytest.mark.slow
def test_lego_orbit_through_ingest(lego_dir, tmp_path):
    """80 lego views as an image folder -> `dronecap ingest` -> `dronecap sfm --gt`.

    Ingest's default selection keeps 21 of the 80 views and 16 of them register (76 %);
    `--min-motion 2` keeps 40 and all register (ATE ~1.1 %).
    """
    import cv2

    ds, gt = blender_flight(lego_dir, count=80)
    folder = tmp_path / "orbit"
    folder.mkdir()
    for i, im in enumerate(ds.images):
        cv2.imwrite(str(folder / f"{i:04d}.png"), im[..., 0])
    (tmp_path / "poses.json").write_text(json.dumps(gt))
    k = ds.intrinsics
    intr = f"{k.fx},{k.fy},{k.cx},{k.cy}"
    work = ["--workdir", str(tmp_path)]
    # white background: most pixels are clipped, which ingest would call over-exposed
    ingest = [
        "ingest",
        str(folder),
        "--intrinsics",
        intr,
        "--max-clipped",
        "1.0",
        "--min-motion",
        "2",
        *work,
    ]
    assert cli_main(ingest) == 0
    code = cli_main(["sfm", "--gt", str(tmp_path / "poses.json"), "--quiet", *work])
    assert code == 0
    report = json.loads((tmp_path / "sfm" / "report.json").read_text())
    assert report["accuracy"]["registration_rate"] >= 0.9
    assert report["accuracy"]["ate_percent"] <= 2.0


def test_points_ply_has_colours_and_the_model_is_not_bent(lego_run):
    """points.ply: pycolmap's export of the kept points, in the scene frame, with colours; the
    bend check (model vs two-view rotations, no ground truth) passes on a straight model."""
    import open3d as o3d

    tmp, report, _ = lego_run
    cloud = o3d.io.read_point_cloud(str(tmp / "sfm" / "points.ply"))
    assert len(cloud.points) == report["quality"]["points_kept"]
    assert cloud.has_colors() and np.asarray(cloud.colors).max() > 0.1
    lo, hi = open_dataset(tmp / "posed.h5", kinds=("posed",)).aabb
    inside = np.all((np.asarray(cloud.points) > lo) & (np.asarray(cloud.points) < hi), axis=1)
    assert inside.mean() > 0.95
    bend = report["bend_check"]
    assert bend["pairs"] >= 20 and not bend["bent"]
    assert bend["median_deg"] < 1.0


def test_video_options_are_checked():
    for bad in ({"ba_global_ratio": 1.0}, {"ba_refinements": 0}, {"time_cap": -1.0}):
        with pytest.raises(ValueError):
            SfmOptions(**bad).validate()
