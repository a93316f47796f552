"""Feature tracks and the pair measures (survival, motion, parallax)."""

from __future__ import annotations

import cv2
import numpy as np

from dronecap.capture.tracks import FeatureTracker, pair_measures
from tests.capture.conftest import pan

RNG = np.random.default_rng(0)
PTS = RNG.uniform(10, 150, (100, 2))


def measures(dst: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """Pair measures from a frame with the 100 tracks PTS to one where ``keep`` of them
    survived (at ``dst``) and new ones (at random places) replaced the others."""
    keep = np.ones(100, bool) if keep is None else keep
    past = np.where(keep[:, None], PTS, np.nan)[:, None, :]  # the replacements did not exist
    points = np.where(keep[:, None], dst, RNG.uniform(10, 150, (100, 2)))
    return pair_measures(past, np.array([100.0]), points, 160)[:, 0]


def test_a_homography_leaves_no_parallax():
    # A camera rotation about its centre (f = 120 px, 4 degrees of yaw) maps the image by
    # K R K^-1: every track moves, none has parallax.
    k = np.array([[120.0, 0, 80], [0, 120, 80], [0, 0, 1]])
    c, s = np.cos(np.radians(4)), np.sin(np.radians(4))
    h = k @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.linalg.inv(k)
    dst = cv2.perspectiveTransform(PTS.reshape(-1, 1, 2), h).reshape(-1, 2)
    survival, motion, parallax = measures(dst)
    assert survival == 1.0 and motion > 8.0  # 120 px * tan(4 deg) = 8.4 px at the centre
    assert parallax < 0.01


def test_depth_differences_show_as_parallax():
    # Half the tracks (near) move 3 px to the right, half (far) 1 px: no homography maps both,
    # the best one leaves each half about 1 px off.
    near = np.arange(100) % 2 == 0
    dst = PTS + np.where(near, 3.0, 1.0)[:, None] * [1.0, 0.0]
    survival, motion, parallax = measures(dst)
    assert abs(motion - 2.0) < 1e-9  # median of fifty 1s and fifty 3s
    assert 0.8 < parallax < 1.2


def test_survival_counts_the_tracks_both_frames_share():
    keep = np.arange(100) < 60
    survival, motion, parallax = measures(PTS + [2.0, 0.0], keep)
    assert survival == 0.6 and abs(motion - 2.0) < 1e-9 and parallax < 0.01
    # Fewer than 12 shared tracks: survival only.
    keep = np.arange(100) < 8
    survival, motion, parallax = measures(PTS + [2.0, 0.0], keep)
    assert survival == 0.08 and np.isnan(motion) and np.isnan(parallax)


def test_tracker_on_a_pan_and_a_skipped_frame():
    frames = pan(10, (160, 160), 2.0)
    tracker = FeatureTracker(window=4)
    for i, f in enumerate(frames):
        tracker.update(None if i == 5 else f)
    t = tracker.tables()
    assert t["pair_motion"].shape == (10, 4)
    # Frame 9 against 8, 7, 6 (2, 4, 6 px) and 5 (skipped: unknown).
    np.testing.assert_allclose(t["pair_motion"][9, :3], [2.0, 4.0, 6.0], atol=0.1)
    assert np.isnan(t["pair_motion"][9, 3]) and np.isnan(t["pair_survival"][5]).all()
    assert (t["pair_parallax"][9, :3] < 0.1).all()  # a pan is a homography
    # Tracks leave the frame at 2 px per frame on the left edge: survival falls with distance.
    assert 1.0 >= t["pair_survival"][9, 0] >= t["pair_survival"][9, 2] > 0.8
