"""Per-frame quality scores of an output (e.g. 160x160) gray frame, judged on the subject.

All scores are computed on the frame as it will be stored, so they describe what SfM and the
trainer see. Brightness-dependent numbers are in 8-bit digital numbers (DN, 0..255).

The *subject* of a frame is where it has texture: pixels whose gradient (after a 3x3 Gaussian)
exceeds ``DETAIL_GRADIENT`` DN/px, grown by 2 px. A uniform backdrop (white, black, sky) is not
subject, so it neither counts as detail nor dilutes the blur measure.

- ``sharpness``: energy of the Laplacian over energy of the gradient of the lightly smoothed
  frame (1/px^2). Blur removes fine scales faster than coarse ones, so this falls when a frame
  is blurred; it does not depend on exposure gain, contrast or how much of the frame the subject
  fills (flat areas add nothing to either energy), and fine texture (fur, gravel) raises it
  rather than lowering it.
- ``brightness``: mean (DN); ``contrast``: standard deviation (DN).
- ``clipped``: fraction of pixels at <= 2 or >= 253 DN (under/over-exposed, or a saturated
  backdrop: the selection tells them apart with ``detail``).
- ``detail``: fraction of the frame that is subject (0..1).
- ``corners``: FAST corners (intensity threshold ``CORNER_THRESHOLD`` DN, non-maximum
  suppression) on the contrast-normalised frame (:mod:`.contrast`, what the tracker and SfM's
  CLAHE retry see): a frame with a handful has nothing SIFT can match however textured it looks
  (a wall seen from close by: 3-6 on Himax test_10's last frames, where SIFT finds 0-4
  keypoints; >= 59 on every usable frame checked, dimmed to 40 % included).
- ``frame_diff``: mean absolute difference to the previous decoded frame (DN, computed by the
  ingest loop); ~0 for a frozen (repeated) frame.
"""

from __future__ import annotations

import numpy as np

from dronecap.capture.contrast import normalize_contrast

SCORE_NAMES = ("sharpness", "brightness", "contrast", "clipped", "detail", "corners", "frame_diff")
DETAIL_GRADIENT = 6.0  # DN per pixel: weaker gradients are noise or shading, not texture
CORNER_THRESHOLD = 20  # DN: FAST's centre-to-circle intensity difference


def frame_scores(gray: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """(sharpness, brightness, contrast, clipped, detail, corners) of one uint8 [H, W] frame."""
    import cv2

    mean, std = cv2.meanStdDev(gray)
    brightness, contrast = float(mean[0, 0]), float(std[0, 0])
    smooth = cv2.GaussianBlur(gray, (3, 3), 0).astype(np.float32)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=1)
    grad2 = gx * gx + gy * gy
    lap = cv2.Laplacian(smooth, cv2.CV_32F, ksize=1)
    sharpness = float(np.mean(lap * lap)) / max(float(np.mean(grad2)), 1e-6)
    textured = (grad2 > (2.0 * DETAIL_GRADIENT) ** 2).astype(np.uint8)  # Sobel ksize 1: 2x
    subject = cv2.dilate(textured, np.ones((5, 5), np.uint8))
    detail = float(subject.mean())
    hist = cv2.calcHist([gray], [0], None, [256], [0, 256])
    clipped = float(hist[:3].sum() + hist[253:].sum()) / gray.size
    fast = cv2.FastFeatureDetector_create(CORNER_THRESHOLD)
    corners = float(len(fast.detect(normalize_contrast(gray))))
    return sharpness, brightness, contrast, clipped, detail, corners


def frame_diff(prev: np.ndarray | None, gray: np.ndarray) -> float:
    """Mean absolute difference (DN) of two uint8 [H, W] frames; NaN without ``prev``."""
    import cv2

    if prev is None:
        return float("nan")
    return float(cv2.norm(prev, gray, cv2.NORM_L1)) / gray.size
