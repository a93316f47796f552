"""Contrast normalisation for feature detection on low-contrast, vignetted nano-drone frames.

Himax HM01B0 frames are dim, low in contrast and strongly vignetted; SIFT's contrast threshold
then finds few keypoints away from the centre. CLAHE (contrast-limited adaptive histogram
equalisation, OpenCV) equalises each tile of the image separately, which also flattens the
vignetting. The same function is used wherever dronecap computes features (ingest's motion
tracking, SfM's feature extraction), so the two see the same image. The stored frames are never
changed: the trainer learns the real pixel values.
"""

from __future__ import annotations

import numpy as np

CLIP_LIMIT = 2.0  # CLAHE clip limit (OpenCV's default is 40: far too strong on 160 px frames)
TILES = 4  # tiles per side: 40x40-pixel tiles on a 160x160 frame


def normalize_contrast(gray: np.ndarray, clip_limit: float = CLIP_LIMIT, tiles: int = TILES):
    """CLAHE of one uint8 gray image [H, W] (or [H, W, 1]) -> uint8 [H, W]."""
    import cv2

    img = np.ascontiguousarray(gray.reshape(gray.shape[0], gray.shape[1]))
    clahe = cv2.createCLAHE(clipLimit=float(clip_limit), tileGridSize=(int(tiles), int(tiles)))
    return clahe.apply(img)
