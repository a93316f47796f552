"""Keyframes of a dense flight (sfm/keyframes.py) and the bend check's fold test (sfm/bend.py),
on a real mapped corridor flight."""

from __future__ import annotations

import shutil

import numpy as np
import pycolmap
import pytest

from dronecap.sfm.bend import rotation_disagreement
from dronecap.sfm.keyframes import PAIR_FILE, keyframes
from dronecap.sfm.options import SfmOptions


def test_keyframes_skip_frames_that_barely_moved():
    # frame i and j moved 0.5 px per frame between them; at most 2 px -> every 4th frame
    flow = {(i, j): 0.5 * (j - i) for i in range(20) for j in range(i + 1, min(i + 6, 20))}
    assert keyframes(flow, 20, 5, 2.0) == [0, 4, 8, 12, 16, 19]
    # at most `gap_max` apart however little they moved
    assert keyframes(flow, 20, 5, 100.0) == [0, 5, 10, 15, 19]
    # a frame that moved more than allowed (or has no verified pair) is the next keyframe
    assert keyframes(flow, 20, 5, 0.1) == list(range(20))
    assert keyframes({}, 4, 5, 2.0) == [0, 1, 2, 3]
    assert keyframes(flow, 1, 5, 2.0) == [0] and keyframes(flow, 0, 5, 2.0) == []


def test_a_negative_keyframe_flow_is_refused():
    with pytest.raises(ValueError, match="keyframe_flow"):
        SfmOptions(keyframe_flow=-1.0).validate()


@pytest.fixture(scope="module")
def mapped_by_keyframes(corridor, tmp_path_factory):
    """The corridor flight (89 kept frames, consecutive frames 5.7 px apart) mapped from
    keyframes up to 8 px apart."""
    from dronecap.sfm.pipeline import run_sfm

    out = tmp_path_factory.mktemp("keyframes")
    opts = SfmOptions(exhaustive_below=0, keyframes_above=50, keyframe_flow=8.0)
    report = run_sfm(
        corridor / "frames.h5",
        out / "posed.h5",
        out / "sfm",
        opts,
        corridor / "flight.json",
        progress=False,
    )
    return report, out / "sfm"


@pytest.mark.slow
def test_a_flight_mapped_from_its_keyframes_registers_every_frame_accurately(
    mapped_by_keyframes,
):
    report, sfm = mapped_by_keyframes
    kf = report["keyframes"]
    assert 10 < kf["keyframes"] < kf["frames"] == report["frames_total"]
    assert kf["pairs"] > 0 and (sfm / "work" / PAIR_FILE).exists()
    assert report["registration_rate"] >= 0.99
    assert report["accuracy"]["ate_percent"] < 1.0
    assert report["accuracy"]["rot_median_deg"] < 1.0
    assert not report["bend_check"]["bent"]


def _turned(model: pycolmap.Reconstruction, frames: list[int], deg: float) -> None:
    """Turn the cameras of ``frames`` (indices in name order) by ``deg`` about their y axis."""
    regs = sorted(model.reg_image_ids(), key=lambda i: model.images[i].name)
    turn = pycolmap.Rigid3d(
        pycolmap.Rotation3d(
            np.array([0.0, np.sin(np.radians(deg) / 2), 0.0, np.cos(np.radians(deg) / 2)])
        ),
        np.zeros(3),
    )
    for k in frames:
        frame = model.frames[model.images[regs[k]].frame_id]
        frame.rig_from_world = turn * frame.rig_from_world


@pytest.mark.slow
def test_the_bend_check_calls_a_fold_and_a_wrong_frame_bent_but_not_the_straight_model(
    mapped_by_keyframes, tmp_path
):
    _, sfm = mapped_by_keyframes
    db = sfm / "work" / "database.db"
    straight = rotation_disagreement(db, sfm / "model")
    assert straight["pairs"] > 50 and not straight["bent"]
    model = pycolmap.Reconstruction(sfm / "model")
    n = model.num_reg_images()
    for name, frames in (("fold", list(range(n // 2, n))), ("one frame", [n // 2])):
        rec = pycolmap.Reconstruction(sfm / "model")
        _turned(rec, frames, 40.0)
        shutil.rmtree(tmp_path / name, ignore_errors=True)
        (tmp_path / name).mkdir()
        rec.write(tmp_path / name)
        record = rotation_disagreement(db, tmp_path / name)
        assert record["bent"] and record["max_deg"] > 30, name
