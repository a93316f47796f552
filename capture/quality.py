"""Per-frame quality scores of an output (e.g. 160x160) gray frame, and frame-to-frame motion.

All scores are computed on the frame as it will be stored, so they describe what SfM and the
trainer see. Brightness-dependent numbers are in 8-bit digital numbers (DN, 0..255).

- ``sharpness``: variance of the Laplacian of the lightly smoothed frame (3x3 Gaussian, then
  3x3 Laplacian), divided by the squared mean brightness. Dividing by brightness squared makes it
  invariant to exposure gain (both scale by gain^2), so a darker frame of the same view scores
  the same; the light smoothing keeps sensor noise from passing as detail.
- ``brightness``: mean (DN); ``contrast``: standard deviation (DN).
- ``clipped``: fraction of pixels at <= 2 or >= 253 DN (under/over-exposed).
- ``frame_diff``: mean absolute difference to the previous decoded frame (DN); ~0 for a frozen
  (repeated) frame.
- ``motion``: median displacement (pixels of the output frame) of corner features tracked from
  the previous decoded frame with pyramidal Lucas-Kanade, on a half-size copy (80x80 for a
  160x160 frame: 4x cheaper than full size, within 0.05 px median of it on the simulated
  corridor); phase correlation when fewer than ``MIN_TRACKS`` features track (nearly
  textureless frames); NaN when neither works.
"""

from __future__ import annotations

import numpy as np

SCORE_NAMES = ("sharpness", "brightness", "contrast", "clipped", "frame_diff", "motion")
MIN_TRACKS = 8


def frame_scores(gray: np.ndarray) -> tuple[float, float, float, float]:
    """(sharpness, brightness, contrast, clipped) of one uint8 [H, W] frame; see module doc."""
    import cv2

    mean, std = cv2.meanStdDev(gray)
    brightness, contrast = float(mean[0, 0]), float(std[0, 0])
    lap = cv2.Laplacian(cv2.GaussianBlur(gray, (3, 3), 0), cv2.CV_32F, ksize=1)
    _, lap_std = cv2.meanStdDev(lap)
    sharpness = float(lap_std[0, 0]) ** 2 / max(brightness, 1.0) ** 2
    hist = cv2.calcHist([gray], [0], None, [256], [0, 256])
    clipped = float(hist[:3].sum() + hist[253:].sum()) / gray.size
    return sharpness, brightness, contrast, clipped


class MotionTracker:
    """Feature motion between consecutive frames: call :meth:`update` once per frame in order."""

    def __init__(self, max_features: int = 32) -> None:
        self.max_features = max_features
        self._prev: np.ndarray | None = None
        self._prev_small: np.ndarray | None = None
        self._pts: np.ndarray | None = None

    def update(self, gray: np.ndarray) -> tuple[float, float]:
        """Motion from the previous frame to ``gray`` (uint8 [H, W]).

        Returns:
            (motion, frame_diff): median feature displacement in pixels of ``gray`` (NaN for the
            first frame or when nothing can be tracked) and mean absolute difference in DN (NaN
            for the first frame).
        """
        import cv2

        scale = 2 if min(gray.shape) >= 64 else 1
        small = gray
        if scale == 2:
            small = cv2.resize(
                gray, (gray.shape[1] // 2, gray.shape[0] // 2), interpolation=cv2.INTER_AREA
            )
        motion = diff = float("nan")
        if self._prev is not None and self._prev_small is not None:
            diff = float(cv2.norm(self._prev, gray, cv2.NORM_L1)) / gray.size
            motion = scale * _track(self._prev_small, small, self._pts)
        self._prev, self._prev_small = gray, small
        self._pts = cv2.goodFeaturesToTrack(
            small, self.max_features, qualityLevel=0.01, minDistance=3, blockSize=3
        )
        return motion, diff


def _track(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray | None) -> float:
    import cv2

    if pts is not None and len(pts) >= MIN_TRACKS:
        nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts, None, winSize=(9, 9), maxLevel=2)
        ok = status.ravel() == 1
        if ok.sum() >= MIN_TRACKS:
            d = (nxt - pts).reshape(-1, 2)[ok]
            return float(np.median(np.hypot(d[:, 0], d[:, 1])))
    if float(prev.std()) < 1.0 or float(cur.std()) < 1.0:
        return float("nan")  # flat frames: no measurable motion
    (dx, dy), response = cv2.phaseCorrelate(prev.astype(np.float32), cur.astype(np.float32))
    return float(np.hypot(dx, dy)) if response > 0.05 else float("nan")
