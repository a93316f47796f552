"""Feature tracks through a frame sequence, and the viewpoint change between nearby frames.

:class:`FeatureTracker` follows corners (Shi-Tomasi, ``cv2.goodFeaturesToTrack``) from frame to
frame with pyramidal Lucas-Kanade on contrast-normalised frames (CLAHE,
:func:`dronecap.capture.contrast.normalize_contrast`, the same images SfM extracts features
from), drops tracks that fail a forward-backward check, and tops the set up with new corners
away from the live ones. Every track has an id; a frame's tracks are the ids alive in it.

For every frame ``j`` and every earlier frame ``i = j - d`` (``1 <= d <= window``) it measures,
from the tracks the two frames share:

- ``survival``: shared tracks / tracks of frame ``i`` (1: nothing lost; low: the view changed
  so much that the two frames overlap little);
- ``motion``: median track displacement (pixels of the frame);
- ``parallax``: median distance (pixels) of the tracks of ``j`` from where a homography fitted
  to the shared tracks (RANSAC) puts them. A homography explains a camera rotation or a flat
  scene exactly, so what is left is the depth-dependent motion that triangulation needs: an
  object orbited on a uniform backdrop shows parallax while its image barely moves.

These are the ``pair_*`` tables ``[N, window]`` (entry ``[j, d - 1]`` is the pair ``(j - d,
j)``; NaN when unknown) that :mod:`.selection` reads; they are stored in ``frames.h5`` so a
selection can be replayed with other thresholds. Frames passed as ``None`` (unreadable or
defective) are skipped: tracks continue from the last good frame.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from dronecap.capture.contrast import normalize_contrast

WINDOW = 12  # frames back over which pair measures are kept (bounds the selection's max_gap)
MAX_TRACKS = 200  # tracks kept alive per frame (160x160 frames)
MIN_SHARED = 12  # fewer shared tracks: motion and parallax are NaN for the pair
MIN_DISTANCE = 5  # pixels between corners
FB_ERROR = 0.7  # largest forward-backward tracking error (pixels) of a kept track
HOMOGRAPHY_POINTS = 64  # tracks the homography is fitted to (all are measured against it)
PAIR_NAMES = ("pair_survival", "pair_motion", "pair_parallax")


class FeatureTracker:
    """KLT tracks and pair measures; call :meth:`update` once per decoded frame, in order."""

    def __init__(self, window: int = WINDOW, max_tracks: int = MAX_TRACKS) -> None:
        self.window = int(window)
        self.max_tracks = int(max_tracks)
        self._prev: np.ndarray | None = None  # last good frame (contrast-normalised)
        self._pts_next = np.zeros((0, 2), np.float32)  # tracked positions in the new frame
        self._ids = np.zeros(0, np.int64)  # track ids alive in the last good frame
        self._pts = np.zeros((0, 2), np.float32)  # their positions
        self._next_id = 0
        self._history: deque[tuple[np.ndarray, np.ndarray] | None] = deque(maxlen=self.window)
        self.rows: list[np.ndarray] = []  # per frame: float32 [3, window]

    def update(self, gray: np.ndarray | None) -> int:
        """Track into ``gray`` (uint8 [H, W]; None: skip this frame). Returns the live tracks."""
        row = np.full((len(PAIR_NAMES), self.window), np.nan, np.float32)
        if gray is None:
            self.rows.append(row)
            self._history.appendleft(None)
            return 0
        img = normalize_contrast(gray)
        if self._prev is not None and len(self._pts):
            ok = self._track(img)
            self._ids, self._pts = self._ids[ok], self._pts_next[ok]
        self._top_up(img)
        for d, past in enumerate(self._history, start=1):
            if past is not None:
                row[:, d - 1] = pair_measures(past, (self._ids, self._pts))
        self.rows.append(row)
        self._history.appendleft((self._ids.copy(), self._pts.copy()))
        self._prev = img
        return len(self._ids)

    def tables(self) -> dict[str, np.ndarray]:
        """The pair tables, float32 [N, window] each, named as :data:`PAIR_NAMES`."""
        stack = np.stack(self.rows) if self.rows else np.zeros((0, 3, self.window), np.float32)
        return {name: stack[:, k] for k, name in enumerate(PAIR_NAMES)}

    def _track(self, img: np.ndarray) -> np.ndarray:
        """LK from the previous good frame, checked backwards; sets ``_pts_next``; bool mask."""
        import cv2

        lk = {"winSize": (11, 11), "maxLevel": 3}
        p0 = self._pts.reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev, img, p0, None, **lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(img, self._prev, p1, None, **lk)
        fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
        h, w = img.shape
        p1 = p1.reshape(-1, 2)
        inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] < w) & (p1[:, 1] < h)
        self._pts_next = p1
        return (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < FB_ERROR) & inside

    def _top_up(self, img: np.ndarray) -> None:
        """Add corners away from the live tracks until ``max_tracks`` are alive."""
        import cv2

        need = self.max_tracks - len(self._ids)
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
        ids = np.arange(self._next_id, self._next_id + len(new), dtype=np.int64)
        self._next_id += len(new)
        self._ids = np.concatenate([self._ids, ids])
        self._pts = np.concatenate([self._pts, new])


def pair_measures(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]
) -> tuple[float, float, float]:
    """(survival, motion px, parallax px) from frame ``a`` to frame ``b``.

    Each frame is (ids int64 [K], points float32 [K, 2]) with ids in increasing order (tracks
    are only appended, so they are). See the module docstring for the three measures.
    """
    import cv2

    ids_a, pts_a = a
    ids_b, pts_b = b
    if len(ids_a) == 0:
        return float("nan"), float("nan"), float("nan")
    _, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
    survival = len(ia) / len(ids_a)
    if len(ia) < MIN_SHARED:
        return survival, float("nan"), float("nan")
    pa, pb = pts_a[ia], pts_b[ib]
    motion = float(np.median(np.linalg.norm(pb - pa, axis=1)))
    step = max(1, len(pa) // HOMOGRAPHY_POINTS)  # an even subset keeps the fit cheap
    hmat, _ = cv2.findHomography(pa[::step], pb[::step], cv2.USAC_FAST, 1.0)
    if hmat is None:
        return survival, motion, float("nan")
    mapped = cv2.perspectiveTransform(pa.reshape(-1, 1, 2), hmat).reshape(-1, 2)
    parallax = float(np.median(np.linalg.norm(pb - mapped, axis=1)))
    return survival, motion, parallax
