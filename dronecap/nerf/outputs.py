"""Images and videos a run writes: PNG renders, ground truth | render comparisons, orbits."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dronecap.files import atomic_output


def to_uint8(img: np.ndarray) -> np.ndarray:
    """float [H, W, C] in [0, 1] -> uint8 [H, W, C] (rounded, clipped)."""
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str | Path, img: np.ndarray) -> Path:
    """Write float [H, W, C] (C = 1 or 3, RGB) in [0, 1] as a PNG, atomically."""
    import cv2

    u8 = to_uint8(img)
    bgr = u8[..., ::-1] if u8.shape[2] == 3 else u8[..., 0]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr))
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    with atomic_output(path) as tmp:
        Path(tmp).write_bytes(buf.tobytes())
    return Path(path)


def side_by_side(pairs: Sequence[tuple[np.ndarray, np.ndarray]], gap: int = 4) -> np.ndarray:
    """Rows of ``ground truth | render`` [H, W, C] pairs, white gaps -> float [H', W', C]."""
    rows = []
    for gt, pred in pairs:
        h, _, c = gt.shape
        rows.append(np.concatenate([gt, np.ones((h, gap, c), np.float32), pred], 1))
    w, c = rows[0].shape[1], rows[0].shape[2]
    out = []
    for r in rows:
        out += [r, np.ones((gap, w, c), np.float32)]
    return np.concatenate(out[:-1], 0)


def orbit_poses(poses: np.ndarray, centre: np.ndarray, n: int) -> np.ndarray:
    """``n`` camera-to-world poses [n, 4, 4] (OpenCV axes) circling ``centre`` [3].

    The orbit axis is the mean "up" of the given cameras (their -y axes), the radius and
    elevation are the cameras' mean distance and mean height above ``centre`` along that axis.
    """
    up = -poses[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    rel = poses[:, :3, 3] - centre
    height = float(np.mean(rel @ up))
    radius = float(np.mean(np.linalg.norm(rel - np.outer(rel @ up, up), axis=1)))
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    out = np.zeros((n, 4, 4))
    for i, th in enumerate(np.linspace(0.0, 2 * np.pi, n, endpoint=False)):
        eye = centre + radius * (np.cos(th) * a + np.sin(th) * b) + height * up
        z = centre - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        out[i, :3, :3] = np.stack([x, y, z], 1)
        out[i, :3, 3] = eye
        out[i, 3, 3] = 1.0
    return out


def write_video(stem: str | Path, frames: Sequence[np.ndarray], fps: int = 24) -> Path:
    """Write float frames [H, W, C] in [0, 1] as a video a browser plays, atomically: H.264 in
    ``STEM.mp4`` when OpenCV's FFmpeg has the encoder (fourcc avc1), else an animated WebP
    ``STEM.webp`` (Pillow, lossless), else an animated ``STEM.gif``. Returns the path written.

    MPEG-4 Part 2 (mp4v), which every OpenCV build writes, is not used: browsers do not play it.
    """
    import cv2

    stem = Path(stem)
    u8 = [to_uint8(f) for f in frames]
    rgb = [np.repeat(f, 3, axis=2) if f.shape[2] == 1 else f for f in u8]
    h, w = rgb[0].shape[:2]
    path = stem.with_suffix(".mp4")
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"avc1"), fps, (w, h))
    if writer.isOpened():
        try:
            for f in rgb:
                writer.write(f[..., ::-1].copy())
        finally:
            writer.release()
        if tmp.exists() and tmp.stat().st_size > 0:
            os.replace(tmp, path)
            return path
    tmp.unlink(missing_ok=True)
    from PIL import Image, features

    path = stem.with_suffix(".webp" if features.check("webp") else ".gif")
    images = [Image.fromarray(f) for f in rgb]
    with atomic_output(path) as out:
        extra = {"lossless": True} if path.suffix == ".webp" else {}
        ms = round(1000 / fps)
        images[0].save(out, format=path.suffix[1:].upper(), save_all=True,
                       append_images=images[1:], duration=ms, loop=0, **extra)  # fmt: skip
    return path
