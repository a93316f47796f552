"""Fixtures of the capture tests: small videos written with OpenCV's VideoWriter."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A blobby uint8 [h, w] texture with corners at several scales."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for scale in (4, 12, 36):
        small = rng.random((h // scale + 2, w // scale + 2)).astype(np.float32)
        img += cv2.resize(small, (w + 2 * scale, h + 2 * scale))[:h, :w] / scale**0.5
    return cv2.normalize(img, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)


def pan(n: int, size: tuple[int, int], step: float, seed: int = 0) -> list[np.ndarray]:
    """``n`` gray frames of ``size`` (w, h) panning right over a texture by ``step`` px/frame."""
    w, h = size
    tex = texture(h, w + int(np.ceil(step * n)) + 2, seed)
    frames = []
    for i in range(n):
        m = np.float32([[1, 0, -step * i], [0, 1, 0]])
        frames.append(cv2.warpAffine(tex, m, (w, h), flags=cv2.INTER_LINEAR))
    return frames


def write_video(
    path: Path, frames: list[np.ndarray], fps: float = 30.0, fourcc: str = "MJPG"
) -> Path:
    """Write gray (or BGR) frames with cv2.VideoWriter; returns ``path``."""
    h, w = frames[0].shape[:2]
    color = frames[0].ndim == 3
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h), color)
    assert vw.isOpened(), f"cannot write {fourcc} to {path}"
    for f in frames:
        vw.write(f)
    vw.release()
    return path


@pytest.fixture
def pan_video(tmp_path: Path) -> Path:
    """48 frames of 320x240 panning 3 px/frame (2 px/frame at 160x160: crop 240, scale 2/3)."""
    return write_video(tmp_path / "pan.avi", pan(48, (320, 240), 3.0))


def white_orbit_frames(lego: Path, views: range | None = None) -> list[np.ndarray]:
    """The lego test views (an orbit of 200) composited on pure 255 white, as gray uint8 [H, W].

    The object covers a small part of every frame: the rest is a uniform, saturated backdrop.
    """
    names = [f"r_{i}.png" for i in (views if views is not None else range(200))]
    out = []
    for name in names:
        rgba = cv2.imread(str(lego / "test" / name), cv2.IMREAD_UNCHANGED).astype(np.float32)
        alpha = rgba[..., 3:] / 255.0
        bgr = rgba[..., :3] * alpha + 255.0 * (1.0 - alpha)
        out.append(cv2.cvtColor(np.rint(bgr).astype(np.uint8), cv2.COLOR_BGR2GRAY))
    return out
