"""Stream defect detectors on hand-made frames: torn, upside-down, Bayer mosaics."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dronecap.capture.defects import UpsideDownCheck, demosaic, detect_bayer, torn_row
from tests.capture.conftest import pan, texture

H, W = 244, 324  # the Himax QVGA frame


@pytest.fixture
def frames() -> list[np.ndarray]:
    return pan(6, (W, H), 2.0, seed=3)


def shifted(image: np.ndarray, row: int, nbytes: int) -> np.ndarray:
    """The AI-deck's shifted tear, written independently of the simulator: from ``row`` on,
    the rest of the buffer arrives ``nbytes`` early; the buffer's end stays zero."""
    flat = image.reshape(-1)
    out = np.zeros_like(flat)
    start = row * image.shape[1]
    out[:start] = flat[:start]
    rest = flat[start + nbytes :]
    out[start : start + len(rest)] = rest
    return out.reshape(image.shape)


def test_torn_frames_are_found_at_their_row(frames):
    prev, cur = frames[0], frames[1]
    assert torn_row(cur, prev) is None
    for row, fill in ((163, 0), (100, 128), (220, 0)):  # bottom third black, gray, a sliver
        torn = cur.copy()
        torn[row:] = fill
        assert torn_row(torn, prev) == row
    # Shifted: 2048 bytes lost -> the last 2048 bytes (6 rows + 104 px) are zero.
    got = torn_row(shifted(cur, 150, 2048), prev)
    assert got == H - 2048 // W  # the full zero rows at the bottom
    # A torn first frame (no reference): a black or mid-gray bottom third still counts.
    first = cur.copy()
    first[160:] = 128
    assert torn_row(first, None) == 160


def test_uniform_backdrop_is_not_a_tear(frames):
    # An object on white: the bottom rows are 255 in this frame AND the previous one.
    prev, cur = frames[0].copy(), frames[1].copy()
    prev[150:], cur[150:] = 255, 255
    assert torn_row(cur, prev) is None
    assert torn_row(np.full((H, W), 255, np.uint8), None) is None  # all flat: not torn
    # the object moved up out of the bottom rows: white now where it was textured before
    cur[120:] = 255
    assert torn_row(cur, frames[0]) is None
    cur[120:] = 0  # the same rows black: a lost part
    assert torn_row(cur, frames[0]) == 120


def test_upside_down_frame_among_normal_ones(frames):
    check = UpsideDownCheck()
    seq = [f.copy() for f in frames]
    seq[3] = seq[3][::-1, ::-1].copy()
    flags = [check.is_upside_down(f) for f in seq]
    assert flags == [False, False, False, True, False, False]


BAYER_SITES = {  # sensor layout -> the BGR channel of sites (0,0), (0,1), (1,0), (1,1)
    "RGGB": (2, 1, 1, 0),
    "BGGR": (0, 1, 1, 2),
    "GRBG": (1, 2, 0, 1),
    "GBRG": (1, 0, 2, 1),
}


def mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """Sample a BGR image through a Bayer colour filter array with sensor layout ``pattern``."""
    raw = np.zeros(bgr.shape[:2], np.uint8)
    for (r, c), ch in zip(((0, 0), (0, 1), (1, 0), (1, 1)), BAYER_SITES[pattern], strict=True):
        raw[r::2, c::2] = bgr[r::2, c::2, ch]
    return raw


def colour_scene() -> np.ndarray:
    """A smooth colour image: three textures, red brighter than blue on average."""
    b, g, r = (texture(H, W, seed=s).astype(np.float32) for s in (1, 2, 3))
    return np.stack([0.5 * b, 0.8 * g, r], axis=2).astype(np.uint8)


@pytest.mark.parametrize("pattern", sorted(BAYER_SITES))
def test_bayer_mosaic_is_detected_and_demosaiced(pattern):
    bgr = colour_scene()
    raw = mosaic(bgr, pattern)
    assert detect_bayer(raw) == pattern
    out = demosaic(raw, pattern)
    # Bilinear demosaicing of a smooth image: within a few DN of the original colours.
    assert np.abs(out.astype(float) - bgr).mean() < 3.0
    # The swapped-red/blue conversion would be far off: the mapping is right.
    wrong = {"RGGB": "BGGR", "BGGR": "RGGB", "GRBG": "GBRG", "GBRG": "GRBG"}[pattern]
    assert np.abs(demosaic(raw, wrong).astype(float) - bgr).mean() > 10.0


def test_gray_images_are_not_mosaics(frames):
    assert detect_bayer(frames[0]) is None
    assert detect_bayer(cv2.cvtColor(colour_scene(), cv2.COLOR_BGR2GRAY)) is None
