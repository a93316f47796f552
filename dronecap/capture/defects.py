"""Stream defects of drone footage: torn and upside-down frames, and raw Bayer mosaics.

What a nano-drone's Wi-Fi link and sensor deliver (see the telemetry contract and the
simulator's ``stream`` module):

- **torn** frames: packets lost mid-frame, so from some row down the frame is black, mid-gray,
  or the rest of the buffer moved up (zeros fill its end). :func:`torn_row` finds a block of
  flat black or mid-gray rows at the bottom of a frame whose rows were textured in the previous
  good frame (a uniform floor or backdrop that the previous frame also shows is not a tear, nor
  is a white backdrop the object just left: the white-background lego orbit zoomed 1.25x lost
  16 of 58 frames to this before).
- **upside-down** frames: the AI-deck occasionally delivers a frame rotated by 180 degrees.
  :class:`UpsideDownCheck` compares each frame and its 180-degree rotation with the previous
  good frame (normalised cross-correlation of blurred 40x40 thumbnails).
- **Bayer mosaics**: the colour HM01B0 delivers its raw RGGB-family mosaic, which looks like a
  gray image with a 2x2 pattern. :func:`detect_bayer` recognises it (neighbouring pixels differ
  more than pixels two apart, along both axes) and names the pattern; :func:`demosaic` converts
  it with OpenCV's Bayer conversions. Which diagonal holds green is measured (the two green
  sites agree best); which of the two other sites is red cannot be told from gray values, so the
  brighter one is taken as red (override with ``ingest --bayer PATTERN``).

Frames are judged at source resolution (before crop and resize), uint8 [H, W].
"""

from __future__ import annotations

import numpy as np

TEAR_MIN_ROWS = 2  # a flat block must be at least this many rows high (and 1 % of the height)
FLAT_STD = 2.0  # DN: a row this uniform is flat (JPEG ringing stays below)
TEXTURED_STD = 4.0  # DN: a row of the previous frame this varied was content
THUMB = 40  # thumbnail side for the upside-down check
FLIP_MARGIN = 0.2  # the rotated frame must correlate this much better (NCC) with the reference
BAYER_RATIO = 1.15  # |d1| / |d2| above this along both axes: a mosaic, not an image
# Sensor layout of the 2x2 cell (row 0 then row 1) -> OpenCV conversion code name. OpenCV names
# a pattern by the second row's second and third pixels, hence the apparent swap.
BAYER_CODES = {
    "RGGB": "COLOR_BayerBG2BGR",
    "BGGR": "COLOR_BayerRG2BGR",
    "GRBG": "COLOR_BayerGB2BGR",
    "GBRG": "COLOR_BayerGR2BGR",
}


def torn_row(gray: np.ndarray, reference: np.ndarray | None) -> int | None:
    """First row of the lost bottom part of ``gray`` (uint8 [H, W]), or None when not torn.

    ``reference`` is the previous good frame of the same size (None: first frame; only a black
    or mid-gray block of at least a tenth of the frame counts then).
    """
    h = gray.shape[0]
    rows = gray.astype(np.float32)
    std, mean = rows.std(axis=1), rows.mean(axis=1)
    flat = std < FLAT_STD
    if not flat[-1]:
        return None
    top = h - int(np.argmin(flat[::-1])) if not flat.all() else 0
    if top == 0:
        return None  # the whole frame is flat: blank or black, not torn
    value = float(np.median(mean[top:]))
    same = np.abs(mean[top:] - value) < 3.0
    top = h - int(np.argmin(same[::-1])) if not same.all() else top
    height = h - top
    if height < max(TEAR_MIN_ROWS, 0.01 * h):
        return None
    if not (value < 3.0 or abs(value - 128.0) < 3.0):
        return None  # a lost part is black, mid-gray or zeros: a white backdrop is content
    if reference is None:
        return top if height >= 0.1 * h else None
    ref = reference.astype(np.float32)[top:]
    textured = ref.std(axis=1) > TEXTURED_STD
    return top if textured.mean() > 0.5 else None


def _thumb(gray: np.ndarray) -> np.ndarray:
    import cv2

    small = cv2.resize(gray, (THUMB, THUMB), interpolation=cv2.INTER_AREA).astype(np.float32)
    small = cv2.GaussianBlur(small, (5, 5), 0)
    small -= small.mean()
    return small / max(float(np.linalg.norm(small)), 1e-6)


class UpsideDownCheck:
    """Call :meth:`is_upside_down` on the frames in order; the reference is the last upright
    frame it saw (frames judged upside down do not replace it)."""

    def __init__(self) -> None:
        self._ref: np.ndarray | None = None

    def is_upside_down(self, gray: np.ndarray) -> bool:
        """True when ``gray`` (uint8 [H, W]) matches the reference far better rotated 180°."""
        t = _thumb(gray)
        if self._ref is None:
            self._ref = t
            return False
        upright = float((t * self._ref).sum())
        rotated = float((t[::-1, ::-1] * self._ref).sum())
        if rotated > upright + FLIP_MARGIN and rotated > 0.5:
            return True
        self._ref = t
        return False


def detect_bayer(gray: np.ndarray) -> str | None:
    """The Bayer pattern of a raw mosaic fed as gray (uint8 [H, W], even size), else None."""
    g = gray.astype(np.float32)
    h, w = (g.shape[0] // 2) * 2, (g.shape[1] // 2) * 2
    if h < 4 or w < 4:  # too small to tell a mosaic from texture
        return None
    g = g[:h, :w]
    d1x = np.abs(np.diff(g, axis=1)).mean()
    d2x = np.abs(g[:, 2:] - g[:, :-2]).mean()
    d1y = np.abs(np.diff(g, axis=0)).mean()
    d2y = np.abs(g[2:] - g[:-2]).mean()
    if not (d1x > BAYER_RATIO * d2x and d1y > BAYER_RATIO * d2y):
        return None
    sites = {(r, c): g[r::2, c::2] for r in (0, 1) for c in (0, 1)}
    main = np.abs(sites[0, 0] - sites[1, 1]).mean()  # the two sites on the main diagonal
    anti = np.abs(sites[0, 1] - sites[1, 0]).mean()
    if anti < main:  # green on the anti-diagonal: R and B on the main one
        return "RGGB" if sites[0, 0].mean() >= sites[1, 1].mean() else "BGGR"
    return "GRBG" if sites[0, 1].mean() >= sites[1, 0].mean() else "GBRG"


def demosaic(raw: np.ndarray, pattern: str) -> np.ndarray:
    """BGR uint8 [H, W, 3] of a raw mosaic uint8 [H, W] with sensor layout ``pattern``."""
    import cv2

    return cv2.cvtColor(raw, getattr(cv2, BAYER_CODES[pattern]))
