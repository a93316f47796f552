"""Selection rules on hand-made score tables (no decoding)."""

from __future__ import annotations

import numpy as np

from dronecap.capture.selection import (
    BLACK,
    BLURRY,
    FROZEN,
    KEPT,
    KEPT_GAP,
    REASONS,
    SelectionParams,
    select_frames,
)


def tables(motion: np.ndarray, **over: np.ndarray) -> dict[str, np.ndarray]:
    """Score tables of N good frames with the given per-frame motion (pixels)."""
    n = len(motion)
    t = {
        "sharpness": np.full(n, 0.02),
        "brightness": np.full(n, 120.0),
        "contrast": np.full(n, 40.0),
        "clipped": np.zeros(n),
        "frame_diff": np.full(n, 5.0),
        "motion": np.asarray(motion, float),
        "source_index": np.arange(n),
    }
    t.update(over)
    return t


def kept(sel) -> np.ndarray:
    return np.flatnonzero(sel.keep)


def test_steady_motion_keeps_every_min_motion_pixels():
    # 1 px per frame, min_motion 5 px: one frame in five.
    sel = select_frames(tables(np.ones(50)), SelectionParams(min_motion=5.0, lookahead=1))
    assert np.all(np.diff(kept(sel)) == 5)
    assert set(sel.reason[kept(sel)]) == {KEPT}


def test_sharp_frame_beats_its_blurred_twin():
    # Frames come in pairs seeing the same view (motion 0 inside a pair, 4 px between pairs);
    # the first of each pair is blurred to 0.7x sharpness (not "blurry", still usable).
    n = 40
    motion = np.where(np.arange(n) % 2 == 0, 4.0, 0.0)
    sharp = np.where(np.arange(n) % 2 == 0, 0.014, 0.02)
    sel = select_frames(tables(motion, sharpness=sharp), SelectionParams(min_motion=4.0))
    assert len(kept(sel)) >= 15
    assert np.all(kept(sel) % 2 == 1)  # always the sharp twin


def test_blurry_frames_are_dropped_against_their_neighbours():
    sharp = np.full(40, 0.02)
    sharp[[10, 25]] = 0.005  # 1/4 of the local median < blur_ratio 0.6
    sel = select_frames(tables(np.ones(40), sharpness=sharp), SelectionParams())
    assert sel.reason[10] == BLURRY and sel.reason[25] == BLURRY
    assert not sel.keep[[10, 25]].any()


def test_hovering_is_thinned_but_covered():
    # 100 frames moving 2 px, 100 hovering (0.05 px jitter), 100 moving.
    motion = np.r_[np.full(100, 2.0), np.full(100, 0.05), np.full(100, 2.0)]
    p = SelectionParams(min_motion=6.0, max_gap=20)
    sel = select_frames(tables(motion), p)
    k = kept(sel)
    moving = ((k < 100) | (k >= 200)).sum() / 200
    hover = ((k >= 100) & (k < 200)).sum() / 100
    assert moving >= 1 / 3 - 0.02  # one frame per 3 frames of 2 px
    assert hover <= 1 / 15  # only the gap rule keeps frames: about one per 20
    assert np.diff(k).max() <= p.max_gap
    assert (sel.reason[k[(k >= 110) & (k < 190)]] == KEPT_GAP).all()


def test_no_gap_longer_than_max_gap_unless_nothing_is_usable():
    rng = np.random.default_rng(1)
    motion = rng.exponential(0.3, 500)
    for max_gap in (3, 10, 40):
        sel = select_frames(tables(motion), SelectionParams(min_motion=50.0, max_gap=max_gap))
        assert np.diff(kept(sel)).max() <= max_gap
    # A black stretch of 30 frames cannot be covered: the gap is reported.
    bright = np.full(100, 120.0)
    bright[40:70] = 2.0
    sel = select_frames(tables(np.ones(100), brightness=bright), SelectionParams(max_gap=10))
    assert (sel.reason[40:70] == BLACK).all()
    assert len(sel.gaps) == 1 and sel.gaps[0][0] < 40 and sel.gaps[0][1] >= 70


def test_target_count_is_reached_from_below():
    motion = np.random.default_rng(2).uniform(0.5, 1.5, 600)
    for target in (50, 120):
        sel = select_frames(tables(motion), SelectionParams(target=target, max_gap=30))
        assert target - 3 <= sel.keep.sum() <= target


def test_frozen_frames_and_legend():
    diff = np.full(20, 5.0)
    diff[5:9] = 0.0  # repeated frames from a stalled stream
    sel = select_frames(tables(np.ones(20), frame_diff=diff), SelectionParams())
    assert (sel.reason[5:9] == FROZEN).all()
    assert REASONS[FROZEN] == "frozen" and REASONS[KEPT] == "kept"
    assert sum(sel.counts().values()) == 20


def test_zero_min_motion_keeps_every_usable_frame() -> None:
    """min_motion = 0 asks for every usable frame; it used to crash on an empty start pool."""
    sel = select_frames(tables(np.full(12, 1.0)), SelectionParams(min_motion=0.0))
    assert sel.keep.all()
