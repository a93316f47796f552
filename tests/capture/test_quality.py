"""Quality scores judge the subject: fine texture is not blur, a backdrop is not detail."""

from __future__ import annotations

import cv2
import numpy as np

from dronecap.capture.quality import frame_scores
from tests.capture.conftest import texture


def sharpness(img: np.ndarray) -> float:
    return frame_scores(img)[0]


def test_blur_lowers_sharpness_and_fine_texture_does_not():
    tex = texture(160, 160, seed=4)
    blurred = cv2.GaussianBlur(tex, (0, 0), 1.5)
    assert sharpness(blurred) < 0.75 * sharpness(tex)  # caught by the default blur_ratio
    # A close-up of fine texture (fur, gravel): only small-scale detail, no large blobs.
    noise = np.random.default_rng(5).random((160, 160)).astype(np.float32)
    fine = cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 0.8), None, 20, 235, cv2.NORM_MINMAX)
    fine = fine.astype(np.uint8)
    assert sharpness(fine) > sharpness(tex)
    # Exposure gain does not change it (both energies scale with gain squared).
    dark = np.rint(tex * 0.5).astype(np.uint8)
    assert abs(sharpness(dark) / sharpness(tex) - 1.0) < 0.1


def test_a_white_backdrop_is_clipped_but_not_detail():
    frame = np.full((160, 160), 255, np.uint8)
    frame[60:100, 50:110] = texture(40, 60, seed=6)  # a textured object on white
    _, _, _, clipped, detail, corners = frame_scores(frame)
    assert corners > 20  # the object's corners: not blank
    assert clipped > 0.85  # 1 - 2400 / 25600 of the pixels are 255
    # The subject: the object (9.4 % of the frame) and a 2-px margin, nothing of the backdrop.
    assert 0.09 < detail < 0.14
    # The backdrop adds nothing to the blur measure: same sharpness as the object alone.
    alone = frame_scores(np.ascontiguousarray(frame[50:110, 40:120]))[0]
    assert abs(sharpness(frame) / alone - 1.0) < 1e-4


def test_a_smooth_close_up_has_no_corners():
    # Textured at every scale: hundreds of corners; only the large-scale shading left (a wall
    # from close by, Gaussian sigma 4 px): almost none, whatever CLAHE does to its contrast.
    tex = texture(160, 160, seed=4)
    assert frame_scores(tex)[5] > 200
    assert frame_scores(cv2.GaussianBlur(tex, (0, 0), 4))[5] < 20
