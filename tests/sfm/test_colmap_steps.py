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


def _ranked(measured, **opts):
    from dronecap.sfm.initial_pair import PairCandidate, rank_initial_pairs

    ranked = rank_initial_pairs([PairCandidate(*m) for m in measured], SfmOptions(**opts))
    return [(c.a, c.b) for c in ranked]


def test_initial_pair_needs_triangulation_angle_then_most_inliers():
    measured = [  # inliers, angle, forward motion, image ids
        (400, 0.5, 0.5, 1, 2),  # most inliers: a near-duplicate view (no triangulation angle)
        (150, 9.0, 0.5, 3, 7),  # enough angle, most inliers among those
        (90, 20.0, 0.5, 4, 9),
        (120, 5.0, 0.5, 5, 8),  # under the angle: after those that reach it
    ]
    assert _ranked(measured) == [(3, 7), (4, 9), (5, 8)]
    assert _ranked(measured, init_min_tri_angle=25.0) == [(4, 9), (3, 7), (5, 8)]  # widest first


def test_weak_and_forward_initial_pairs_are_not_offered():
    """The general pairs measured on the simulated aideck corridor (seed 3, frames 36/42 ...):
    the only pairs reaching 8 deg had 18-25 inliers and started bent models (ATE 9.5-12.6 %);
    the pairs with most inliers fly straight along the view, which COLMAP's mapper refuses.
    Offered: the pairs with enough inliers that COLMAP accepts, widest angle first."""
    measured = [
        (222, 4.9, 0.969, 59, 67),  # forward: refused by the mapper
        (121, 3.0, 0.924, 16, 25),
        (117, 5.2, 0.745, 31, 50),
        (60, 3.4, 0.861, 35, 44),
        (25, 16.0, 0.412, 36, 42),  # reaches the angle with too few inliers
        (18, 7.4, 0.028, 27, 36),
    ]
    assert _ranked(measured) == [(31, 50), (35, 44), (16, 25)]
    weak_only = [m for m in measured if m[0] < 50]  # sparse frames: the old rule, among accepted
    assert _ranked(weak_only) == [(36, 42), (27, 36)]
    assert _ranked(measured[:1]) == []  # nothing COLMAP accepts: its own search then
    assert _ranked(measured[:1], init_max_forward_motion=1.0) == [(59, 67)]


def test_initial_pair_thresholds_reach_the_mapper():
    opts = SfmOptions(init_min_num_inliers=40, init_max_forward_motion=0.9)
    m = mapper_options(opts, refine_camera=False)
    assert m.mapper.init_min_num_inliers == 40
    assert m.mapper.init_max_forward_motion == pytest.approx(0.9)
    with pytest.raises(ValueError, match="init_max_forward_motion"):
        SfmOptions(init_max_forward_motion=0.0).validate()


def test_initial_pair_on_real_frames_has_angle_and_stays_local(lego_dir, tmp_path):
    """12 lego views, exhaustive matching: the pair chosen lies within init_max_gap frames and
    its measured median triangulation angle passes the threshold."""
    import cv2
    import pycolmap

    from dronecap.sfm.blender_flight import blender_flight
    from dronecap.sfm.features import extract
    from dronecap.sfm.initial_pair import initial_pairs

    ds, _ = blender_flight(lego_dir, count=12)
    (tmp_path / "images").mkdir()
    names = [f"{i:05d}.png" for i in range(ds.n)]
    for n, im in zip(names, ds.images, strict=True):
        cv2.imwrite(str(tmp_path / "images" / n), im[..., 0])
    opts = SfmOptions(num_threads=1, init_max_gap=6, init_min_tri_angle=4.0)
    k = ds.intrinsics
    camera = ("PINHOLE", [k.fx, k.fy, k.cx, k.cy])
    extract(tmp_path / "db.db", tmp_path / "images", names, opts, [camera])
    pycolmap.match_exhaustive(tmp_path / "db.db", device=pycolmap.Device.cpu)
    pairs, info = initial_pairs(tmp_path / "db.db", opts)
    assert pairs and info["measured"] > 0
    first = pairs[0][1]
    a, b = (int(f[:5]) for f in first["frames"])
    assert 3 <= abs(a - b) <= 6
    assert first["tri_angle_deg"] >= 4.0
    assert first["inliers"] >= opts.init_min_num_inliers
    assert first["forward_motion"] <= opts.init_max_forward_motion


def _frames(folder, textured: bool) -> list[str]:
    """Three 160x160 gray PNGs: smoothed noise (hundreds of SIFT blobs) or a dozen soft dots."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    (folder / "images").mkdir()
    names = [f"{i:05d}.png" for i in range(3)]
    for name in names:
        if textured:
            im = cv2.GaussianBlur(rng.random((160, 160)).astype(np.float32), (0, 0), 1.5)
            im = (im - im.min()) / (im.max() - im.min()) * 255
        else:
            im = np.full((160, 160), 90.0, np.float32)
            for x, y in rng.integers(15, 145, (12, 2)):
                cv2.circle(im, (int(x), int(y)), 3, 200.0, -1)
            im = cv2.GaussianBlur(im, (0, 0), 1.0)
        cv2.imwrite(str(folder / "images" / name), im.astype(np.uint8))
    return names


@pytest.mark.parametrize("textured", [True, False])
def test_sparse_frames_are_extracted_one_octave_finer(tmp_path, textured):
    """Textured frames stay at the asked octave; frames with few keypoints are extracted again
    at -2, and the database then holds the finer keypoints (what matching will see)."""
    import pycolmap

    from dronecap.sfm.features import extract_finer_when_sparse

    names = _frames(tmp_path, textured)
    opts = SfmOptions(num_threads=1)
    keypoints, octave = extract_finer_when_sparse(
        tmp_path / "db.db", tmp_path / "images", names, opts, [None]
    )
    median = sorted(keypoints.values())[1]
    assert octave == (-1 if textured else -2)
    assert (median >= opts.finer_below) == textured
    with pycolmap.Database.open(tmp_path / "db.db") as db:
        stored = {im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()}
    assert stored == keypoints and len(stored) == 3  # one set of images, the finer one
    if not textured:  # the finer pass runs at its own contrast threshold
        strict = SfmOptions(num_threads=1, finer_peak_threshold=0.1)
        fewer, octave = extract_finer_when_sparse(
            tmp_path / "db1.db", tmp_path / "images", names, strict, [None]
        )
        assert octave == -2 and sum(fewer.values()) < sum(keypoints.values())
    if not textured:  # 0 turns the second extraction off
        never = SfmOptions(num_threads=1, finer_below=0)
        _, octave = extract_finer_when_sparse(
            tmp_path / "db0.db", tmp_path / "images", names, never, [None]
        )
        assert octave == -1
