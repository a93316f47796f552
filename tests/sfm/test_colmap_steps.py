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
