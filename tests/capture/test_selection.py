"""Selection rules on hand-made score and track tables (no decoding)."""

from __future__ import annotations

import numpy as np

from dronecap.capture.selection import (
    BLACK,
    BLANK,
    BLURRY,
    CLIPPED,
    FROZEN,
    KEPT,
    KEPT_GAP,
    REASONS,
    TORN,
    UPSIDE_DOWN,
    SelectionParams,
    select_frames,
)

WIDTH = 160.0  # frame width: a track moved this far has left the frame


def tables(
    motion: np.ndarray, parallax: np.ndarray | None = None, window: int = 24, **over: np.ndarray
) -> dict[str, np.ndarray]:
    """Tables of N good frames of a camera panning ``motion`` px per frame (and gaining
    ``parallax`` px per frame of parallax). Pair (j - d, j): motion and parallax are the sums
    over the frames between; the tracks that left the frame are lost (survival)."""
    n = len(motion)
    x = np.cumsum(motion)
    par = np.cumsum(np.zeros(n) if parallax is None else parallax)
    pair = {k: np.full((n, window), np.nan) for k in ("survival", "motion", "parallax")}
    for j in range(n):
        for d in range(1, min(window, j) + 1):
            moved = abs(x[j] - x[j - d])
            pair["motion"][j, d - 1] = moved
            pair["parallax"][j, d - 1] = abs(par[j] - par[j - d])
            pair["survival"][j, d - 1] = max(0.0, 1.0 - moved / WIDTH)
    t = {
        "sharpness": np.full(n, 0.2),
        "brightness": np.full(n, 120.0),
        "contrast": np.full(n, 40.0),
        "clipped": np.zeros(n),
        "detail": np.full(n, 0.5),
        "corners": np.full(n, 200.0),
        "frame_diff": np.full(n, 5.0),
        "source_index": np.arange(n),
    } | {f"pair_{k}": v for k, v in pair.items()}
    t.update(over)
    return t


def kept(sel) -> np.ndarray:
    return np.flatnonzero(sel.keep)


def test_steady_motion_never_spaces_kept_frames_beyond_min_motion():
    # 1 px per frame, min_motion 5 px: the frame 5 px on has changed too much, so the last
    # one before it (4 px) is kept: one frame in four.
    sel = select_frames(tables(np.ones(50)), SelectionParams(min_motion=5.0))
    assert np.all(np.diff(kept(sel)) == 4)
    assert set(sel.reason[kept(sel)]) == {KEPT}


def test_parallax_decides_when_the_image_barely_moves():
    # An object orbited on a backdrop: its image moves 0.5 px per frame (motion alone would
    # keep one frame in nine) but the parallax grows 0.5 px per frame: with min_parallax 1.3
    # the frame at 1.5 px is past it, so every third frame (1.0 px) is kept.
    p = SelectionParams(min_motion=5.0, min_parallax=1.3)
    sel = select_frames(tables(np.full(60, 0.5), np.full(60, 0.5)), p)
    assert np.all(np.diff(kept(sel)) == 2)


def test_kept_neighbours_share_enough_tracks():
    # A fast pan: 60 px per frame loses 37 % of the tracks per frame; min_overlap 0.5 forbids
    # two frames (75 % lost), so every frame is kept although motion says "too far" at once.
    sel = select_frames(tables(np.full(20, 60.0)), SelectionParams(min_motion=1000.0))
    assert sel.keep.all()
    # 10 px per frame with min_survival 0.7 (30 % may be lost = 48 px): kept 4 frames apart.
    sel = select_frames(tables(np.full(40, 10.0)), SelectionParams(min_motion=1000.0))
    assert np.all(np.diff(kept(sel)) == 4)


def test_sharp_frame_beats_its_blurred_twin():
    # Frames come in pairs seeing the same view (motion 0 inside a pair, 2 px between pairs);
    # the first of each pair is a little blurred (0.85x sharpness: not "blurry", still usable).
    n = 40
    motion = np.where(np.arange(n) % 2 == 0, 2.0, 0.0)
    sharp = np.where(np.arange(n) % 2 == 0, 0.17, 0.2)
    sel = select_frames(tables(motion, sharpness=sharp), SelectionParams(min_motion=5.0))
    assert len(kept(sel)) >= 9
    assert np.all(kept(sel) % 2 == 1)  # always the sharp twin


def test_blurry_frames_are_dropped_against_their_neighbours():
    sharp = np.full(40, 0.2)
    sharp[[10, 25]] = 0.1  # half the local median < blur_ratio 0.75
    sel = select_frames(tables(np.ones(40), sharpness=sharp), SelectionParams())
    assert sel.reason[10] == BLURRY and sel.reason[25] == BLURRY
    assert not sel.keep[[10, 25]].any()


def test_a_saturated_backdrop_is_not_over_exposure():
    # Every frame is 70 % white backdrop around a textured subject: nothing is "clipped".
    n = 40
    clipped, detail = np.full(n, 0.7), np.full(n, 0.3)
    sel = select_frames(tables(np.ones(n), clipped=clipped, detail=detail), SelectionParams())
    assert CLIPPED not in sel.reason
    # One frame where exposure also ate the subject (95 % clipped, detail a tenth) is.
    clipped[20], detail[20] = 0.95, 0.03
    sel = select_frames(tables(np.ones(n), clipped=clipped, detail=detail), SelectionParams())
    assert sel.reason[20] == CLIPPED and (sel.reason == CLIPPED).sum() == 1


def test_frames_without_corners_are_blank():
    # A wall seen from close by: textured-looking (detail 12 %) but 5 corners (Himax test_10).
    corners = np.full(30, 200.0)
    corners[25:] = 5.0
    sel = select_frames(tables(np.ones(30), corners=corners), SelectionParams())
    assert (sel.reason[25:] == BLANK).all() and sel.reason[24] != BLANK


def test_hovering_is_thinned_but_covered():
    # 100 frames moving 2 px, 100 hovering (0.05 px jitter), 100 moving.
    motion = np.r_[np.full(100, 2.0), np.full(100, 0.05), np.full(100, 2.0)]
    p = SelectionParams(min_motion=6.0, max_gap=20)
    sel = select_frames(tables(motion), p)
    k = kept(sel)
    moving = ((k < 100) | (k >= 200)).sum() / 200
    hover = ((k >= 100) & (k < 200)).sum() / 100
    assert moving >= 0.5 - 0.02  # 4 px is the most below 6 px: one frame in two
    assert hover <= 1 / 15  # only the gap rule keeps frames: about one per 20
    assert np.diff(k).max() <= p.max_gap
    assert (sel.reason[k[(k >= 110) & (k < 190)]] == KEPT_GAP).all()


def test_no_gap_longer_than_max_gap_unless_nothing_is_usable():
    rng = np.random.default_rng(1)
    motion = rng.exponential(0.3, 500)
    for max_gap in (3, 10, 20):
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
        sel = select_frames(tables(motion), SelectionParams(target=target, max_gap=20))
        assert target - 3 <= sel.keep.sum() <= target


def test_frozen_frames_defects_and_legend():
    diff = np.full(20, 5.0)
    diff[5:9] = 0.0  # repeated frames from a stalled stream
    defect = np.zeros(20, np.int8)
    defect[[12, 15]] = [TORN, UPSIDE_DOWN]
    sel = select_frames(tables(np.ones(20), frame_diff=diff, defect=defect), SelectionParams())
    assert (sel.reason[5:9] == FROZEN).all()
    assert sel.reason[12] == TORN and sel.reason[15] == UPSIDE_DOWN
    assert REASONS[FROZEN] == "frozen" and REASONS[KEPT] == "kept"
    assert REASONS[TORN] == "torn" and REASONS[UPSIDE_DOWN] == "upside_down"
    assert sum(sel.counts().values()) == 20


def test_zero_min_motion_keeps_every_usable_frame() -> None:
    """min_motion = 0 asks for every usable frame."""
    sel = select_frames(tables(np.full(12, 1.0)), SelectionParams(min_motion=0.0))
    assert sel.keep.all()


def test_out_of_range_options_are_named():
    assert SelectionParams().problems() == []
    bad = SelectionParams(max_gap=0, target=-3, min_overlap=1.5, min_motion=float("nan"))
    text = " ".join(bad.problems())
    for flag in ("--max-gap", "--target", "--min-overlap", "--min-motion"):
        assert flag in text
