"""Feature tracks through a frame sequence, and the viewpoint change between nearby frames.

:class:`FeatureTracker` follows corners (Shi-Tomasi, ``cv2.goodFeaturesToTrack``) from frame to
frame with pyramidal Lucas-Kanade on contrast-normalised frames (CLAHE,
:func:`dronecap.capture.contrast.normalize_contrast`, the same images SfM extracts features
from), drops tracks that fail a forward-backward check, and tops the set up with new corners
away from the live ones.

For every frame ``j`` and every earlier frame ``i = j - d`` (``1 <= d <= window``) it measures,
from the tracks the two frames share (a track is never revived, so these are the current
frame's tracks that already existed in frame ``i``):

- ``survival``: shared tracks / tracks of frame ``i`` (1: nothing lost; low: the view changed
  so much that the two frames overlap little);
- ``motion``: median track displacement (pixels of the frame);
- ``parallax``: median distance (pixels) of the tracks of ``j`` from where a homography fitted
  to the shared tracks puts them (least squares, normalised DLT, refitted once without the
  tracks more than max(1 px, twice the median) off). A homography explains a camera rotation or
  a flat scene exactly, so what is left is the depth-dependent motion that triangulation
  needs: an object orbited on a uniform backdrop shows parallax while its image barely moves.

These are the ``pair_*`` tables ``[N, window]`` (entry ``[j, d - 1]`` is the pair ``(j - d,
j)``; NaN when unknown) that :mod:`.selection` reads; they are stored in ``frames.h5`` so a
selection can be replayed with other thresholds. Frames passed as ``None`` (unreadable or
defective) are skipped: tracks continue from the last good frame.
"""

from __future__ import annotations

import numpy as np

from dronecap.capture.contrast import normalize_contrast

WINDOW = 12  # frames back over which pair measures are kept (bounds the selection's max_gap)
MAX_TRACKS = 150  # tracks kept alive per frame (160x160 frames)
MIN_SHARED = 12  # fewer shared tracks: motion and parallax are NaN for the pair
MIN_DISTANCE = 5  # pixels between corners
FB_ERROR = 0.7  # largest forward-backward tracking error (pixels) of a kept track
FIT_TRACKS = 64  # about this many tracks fit each homography (all are measured against it)
PAIR_NAMES = ("pair_survival", "pair_motion", "pair_parallax")


class FeatureTracker:
    """KLT tracks and pair measures; call :meth:`update` once per decoded frame, in order.

    A track is never revived, so the tracks the current frame shares with an earlier one are
    the live tracks that existed then: each live track carries its positions in the previous
    ``window`` decoded frames (NaN before it was found, or in a skipped frame).
    """

    def __init__(self, window: int = WINDOW, max_tracks: int = MAX_TRACKS) -> None:
        self.window = int(window)
        self.max_tracks = int(max_tracks)
        self._prev: np.ndarray | None = None  # last good frame (contrast-normalised)
        self._pts = np.zeros((0, 2), np.float32)  # live tracks: position in the last good frame
        self._past = np.full((0, self.window, 2), np.nan, np.float32)  # [S, W, 2], recent first
        self._counts = np.full(self.window, np.nan)  # tracks alive in each past frame
        self.rows: list[np.ndarray] = []  # per frame: float32 [3, window]

    def update(self, gray: np.ndarray | None) -> int:
        """Track into ``gray`` (uint8 [H, W]; None: skip this frame). Returns the live tracks."""
        if gray is None:
            self.rows.append(np.full((len(PAIR_NAMES), self.window), np.nan, np.float32))
            self._shift(None)
            return 0
        img = normalize_contrast(gray)
        if self._prev is not None and len(self._pts):
            ok, moved = self._track(img)
            self._pts, self._past = moved[ok], self._past[ok]
        self._top_up(img)
        measures = pair_measures(self._past, self._counts, self._pts, max(gray.shape))
        self.rows.append(measures.astype(np.float32))
        self._shift(self._pts)
        self._prev = img
        return len(self._pts)

    def tables(self) -> dict[str, np.ndarray]:
        """The pair tables, float32 [N, window] each, named as :data:`PAIR_NAMES`."""
        stack = np.stack(self.rows) if self.rows else np.zeros((0, 3, self.window), np.float32)
        return {name: stack[:, k] for k, name in enumerate(PAIR_NAMES)}

    def _shift(self, pts: np.ndarray | None) -> None:
        """The frame just processed (None: skipped) becomes the most recent past frame."""
        now = np.full((len(self._past), 1, 2), np.nan, np.float32) if pts is None else pts[:, None]
        self._past = np.concatenate([now, self._past[:, :-1]], axis=1)
        self._counts = np.r_[np.nan if pts is None else len(pts), self._counts[:-1]]

    def _track(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LK from the previous good frame, checked backwards: (kept bool [S], moved [S, 2])."""
        import cv2

        lk = {"winSize": (9, 9), "maxLevel": 2}
        p0 = self._pts.reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev, img, p0, None, **lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(img, self._prev, p1, None, **lk)
        fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
        h, w = img.shape
        p1 = p1.reshape(-1, 2)
        inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] < w) & (p1[:, 1] < h)
        return (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < FB_ERROR) & inside, p1

    def _top_up(self, img: np.ndarray) -> None:
        """Add corners away from the live tracks until ``max_tracks`` are alive."""
        import cv2

        need = self.max_tracks - len(self._pts)
        if need < self.max_tracks // 4:
            return
        mask = np.full(img.shape, 255, np.uint8)
        for x, y in self._pts:
            cv2.circle(mask, (int(x), int(y)), MIN_DISTANCE, 0, -1)
        new = cv2.goodFeaturesToTrack(
            img, need, qualityLevel=0.01, minDistance=MIN_DISTANCE, mask=mask, blockSize=5
        )
        if new is None:
            return
        new = new.reshape(-1, 2).astype(np.float32)
        self._pts = np.concatenate([self._pts, new])
        unseen = np.full((len(new), self.window, 2), np.nan, np.float32)
        self._past = np.concatenate([self._past, unseen])


def pair_measures(
    past: np.ndarray, counts: np.ndarray, points: np.ndarray, size: float
) -> np.ndarray:
    """Survival, motion (px) and parallax (px) from each earlier frame to the current one.

    Args:
        past: float [S, W, 2] positions of the current frame's S tracks in the W earlier frames,
            most recent first; NaN where a track did not exist yet (or the frame was skipped).
        counts: float [W] tracks alive in each earlier frame (NaN: skipped or none).
        points: float [S, 2] the tracks' positions in the current frame.
        size: the frame's larger side in pixels (normalises the homography fit).

    Returns:
        float64 [3, W]: rows survival, motion, parallax (see the module docstring); NaN where
        unknown (a skipped frame; fewer than MIN_SHARED shared tracks for motion and parallax).
    """
    w, s = past.shape[1], past.shape[0]
    shared = np.isfinite(past[:, :, 0]).T  # [W, S]
    src = np.nan_to_num(past.transpose(1, 0, 2).astype(float))
    out = np.full((3, w), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        out[0] = shared.sum(1) / counts
    enough = shared.sum(1) >= MIN_SHARED
    if not enough.any():
        return out
    src, shared = src[enough], shared[enough]
    dst = np.broadcast_to(points.astype(float), src.shape)
    out[1, enough] = _masked_median(np.linalg.norm(dst - src, axis=2), shared)
    # Homography by normalised DLT, refitted once without the tracks far off the first fit.
    scale = 2.0 / size
    fit = slice(None, None, max(1, s // FIT_TRACKS))  # an even subset keeps the fit cheap
    weights = shared.astype(float)
    for _ in range(2):
        hmat = _fit_homography(
            src[:, fit] * scale - 1.0, dst[:, fit] * scale - 1.0, weights[:, fit]
        )
        err = _transfer_error(hmat, src * scale - 1.0, dst * scale - 1.0) / scale
        cut = np.maximum(2.0 * _masked_median(err, shared), 1.0)[:, None]
        weights = (shared & (err <= cut)).astype(float)
    out[2, enough] = _masked_median(err, shared)
    return out


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median over axis 1 of ``values`` [B, S] where ``mask`` [B, S] (NaN where empty)."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)  # masked values sort last
    n = mask.sum(1)
    rows = np.arange(len(n))
    lo, hi = ordered[rows, np.maximum(n - 1, 0) // 2], ordered[rows, np.maximum(n, 1) // 2]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _fit_homography(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least-squares homographies [B, 3, 3] (DLT) mapping src [B, S, 2] to dst."""
    b, s = weights.shape
    rows = np.zeros((b, s, 2, 9))
    rows[:, :, 0, 0:2] = -src
    rows[:, :, 0, 2] = -1.0
    rows[:, :, 1, 3:5] = -src
    rows[:, :, 1, 5] = -1.0
    rows[:, :, :, 6:8] = dst[:, :, :, None] * src[:, :, None, :]
    rows[:, :, :, 8] = dst
    rows = rows.reshape(b, 2 * s, 9)
    normal = np.matmul(rows.transpose(0, 2, 1) * np.repeat(weights, 2, axis=1)[:, None], rows)
    _, vectors = np.linalg.eigh(normal)
    return vectors[..., 0].reshape(-1, 3, 3)


def _transfer_error(hmat: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Distance [B, S] between dst and src [B, S, 2] mapped through hmat [B, 3, 3]."""
    p = np.matmul(src, hmat[:, :, :2].transpose(0, 2, 1)) + hmat[:, None, :, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        mapped = p[..., :2] / p[..., 2:]
    return np.linalg.norm(mapped - dst, axis=2)
