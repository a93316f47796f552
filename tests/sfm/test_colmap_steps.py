"""Mapper settings handed to COLMAP: thresholds sized for 160x160 frames."""

from __future__ import annotations

import pytest

from dronecap.sfm.colmap_steps import mapper_options
from dronecap.sfm.options import SfmOptions


@pytest.mark.parametrize("relaxed", [False, True])
def test_pixel_thresholds_reach_the_mapper(relaxed):
    opts = SfmOptions(max_reproj_error=1.25, abs_pose_max_error=2.5, tri_max_angle_error=0.75)
    m = mapper_options(opts, refine_camera=False, relaxed=relaxed)
    assert m.mapper.filter_max_reproj_error == pytest.approx(1.25)
    assert m.mapper.init_max_error == pytest.approx(1.25)
    assert m.triangulation.merge_max_reproj_error == pytest.approx(1.25)
    assert m.triangulation.complete_max_reproj_error == pytest.approx(1.25)
    assert m.mapper.abs_pose_max_error == pytest.approx(2.5)
    assert m.triangulation.create_max_angle_error == pytest.approx(0.75)
    assert m.triangulation.continue_max_angle_error == pytest.approx(0.75)
    assert m.triangulation.re_max_angle_error == pytest.approx(1.5)


def test_defaults_are_tighter_than_colmaps():
    import pycolmap

    colmap = pycolmap.IncrementalPipelineOptions()
    ours = mapper_options(SfmOptions(), refine_camera=True)
    assert ours.mapper.filter_max_reproj_error < colmap.mapper.filter_max_reproj_error
    assert ours.mapper.abs_pose_max_error < colmap.mapper.abs_pose_max_error
    assert ours.triangulation.create_max_angle_error < colmap.triangulation.create_max_angle_error


@pytest.mark.parametrize("field", ["max_reproj_error", "abs_pose_max_error", "tri_max_angle_error"])
def test_non_positive_threshold_is_rejected(field):
    with pytest.raises(ValueError, match="thresholds must be > 0"):
        SfmOptions(**{field: 0.0}).validate()


def test_initial_pair_needs_triangulation_angle_then_most_inliers():
    from dronecap.sfm.colmap_steps import choose_initial_pair

    measured = [
        (400, 1.5, 1, 2),  # most inliers: a near-duplicate view (no triangulation angle)
        (150, 9.0, 3, 7),  # the winner: enough angle, most inliers among those
        (90, 20.0, 4, 9),
    ]
    assert choose_initial_pair(measured, 8.0) == (150, 9.0, 3, 7)
    assert choose_initial_pair(measured, 25.0) is None  # COLMAP's own choice then


def test_initial_pair_on_real_frames_has_angle_and_stays_local(lego_dir, tmp_path):
    """12 lego views, exhaustive matching: the pair chosen lies within init_max_gap frames and
    its measured median triangulation angle passes the threshold."""
    import cv2
    import pycolmap

    from dronecap.sfm.blender_flight import blender_flight
    from dronecap.sfm.colmap_steps import extract, initial_pair

    ds, _ = blender_flight(lego_dir, count=12)
    (tmp_path / "images").mkdir()
    names = [f"{i:05d}.png" for i in range(ds.n)]
    for n, im in zip(names, ds.images, strict=True):
        cv2.imwrite(str(tmp_path / "images" / n), im[..., 0])
    opts = SfmOptions(num_threads=1, init_max_gap=6, init_min_tri_angle=4.0)
    k = ds.intrinsics
    extract(
        tmp_path / "db.db", tmp_path / "images", names, opts, ("PINHOLE", [k.fx, k.fy, k.cx, k.cy])
    )
    pycolmap.match_exhaustive(tmp_path / "db.db", device=pycolmap.Device.cpu)
    pair, info = initial_pair(tmp_path / "db.db", opts)
    assert pair is not None and info["measured"] > 0
    a, b = (int(f[:5]) for f in info["chosen"]["frames"])
    assert 3 <= abs(a - b) <= 6
    assert info["chosen"]["tri_angle_deg"] >= 4.0
