"""Mapper settings handed to COLMAP: thresholds sized for 160x160 frames."""

from __future__ import annotations

import pytest

from dronecap.sfm.colmap_steps import mapper_options
from dronecap.sfm.options import SfmOptions


@pytest.mark.parametrize("relaxed", [False, True])
def test_pixel_thresholds_reach_the_mapper(relaxed):
    opts = SfmOptions(max_reproj_error=1.25, abs_pose_max_error=2.5, tri_max_angle_error=0.75)
    m = mapper_options(opts, known_camera=True, relaxed=relaxed)
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
    ours = mapper_options(SfmOptions(), known_camera=False)
    assert ours.mapper.filter_max_reproj_error < colmap.mapper.filter_max_reproj_error
    assert ours.mapper.abs_pose_max_error < colmap.mapper.abs_pose_max_error
    assert ours.triangulation.create_max_angle_error < colmap.triangulation.create_max_angle_error


@pytest.mark.parametrize("field", ["max_reproj_error", "abs_pose_max_error", "tri_max_angle_error"])
def test_non_positive_threshold_is_rejected(field):
    with pytest.raises(ValueError, match="thresholds must be > 0"):
        SfmOptions(**{field: 0.0}).validate()


def _database(path, pairs):
    """A COLMAP database of 8 frames named in flight order with the given two-view geometries:
    pairs = [(frame a, frame b, configuration name, inliers), ...]."""
    import numpy as np
    import pycolmap

    with pycolmap.Database.open(path) as db:
        cam = pycolmap.Camera(model="PINHOLE", width=160, height=160, params=[120, 120, 80, 80])
        cid = db.write_camera(cam)
        # written in reverse so that database ids and flight order disagree
        ids = {
            i: db.write_image(pycolmap.Image(name=f"{i:05d}.png", camera_id=cid))
            for i in reversed(range(8))
        }
        for a, b, config, n in pairs:
            g = pycolmap.TwoViewGeometry()
            g.config = getattr(pycolmap.TwoViewGeometryConfiguration, config)
            g.inlier_matches = np.zeros((n, 2), np.uint32)
            db.write_two_view_geometry(ids[a], ids[b], g)
    return ids


def test_initial_pair_skips_planar_and_adjacent_pairs(tmp_path):
    from dronecap.sfm.colmap_steps import epipolar_init_pair

    ids = _database(
        tmp_path / "db.db",
        [
            (0, 5, "PLANAR_OR_PANORAMIC", 300),  # most inliers, but a homography start
            (2, 3, "CALIBRATED", 200),  # general geometry, but adjacent frames
            (1, 4, "CALIBRATED", 80),
            (3, 7, "UNCALIBRATED", 120),  # the winner: general geometry, 4 frames apart
        ],
    )
    assert set(epipolar_init_pair(tmp_path / "db.db")) == {ids[3], ids[7]}


def test_no_general_pair_leaves_the_choice_to_colmap(tmp_path):
    from dronecap.sfm.colmap_steps import epipolar_init_pair

    _database(tmp_path / "db.db", [(0, 5, "PLANAR", 300), (1, 6, "PANORAMIC", 100)])
    assert epipolar_init_pair(tmp_path / "db.db") is None
