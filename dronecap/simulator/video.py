"""Writing gray videos that OpenCV (FFmpeg) can read back, atomically.

Codecs measured on this machine (OpenCV 5 wheel, 160x160 gray, written and read back here):

- ``ffv1`` (default): lossless, any container (.mp4, .mkv, .avi), ~13 kB per 160x160 frame.
  Lossless matters: block artefacts of lossy codecs create and destroy SIFT corners.
- ``mjpg``: intra-frame JPEG, ~1.5 DN mean error, ~5 kB per frame (.avi, .mkv).
- ``mp4v``: MPEG-4 part 2, ~1.7 DN mean error and ~0.6 kB per frame (.mp4); lossy between
  frames, the smallest files.
H.264 (``avc1``) cannot be written by this OpenCV wheel.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from dronecap.errors import InputError, OutputError

CODECS = {"ffv1": "FFV1", "mjpg": "MJPG", "mp4v": "mp4v"}


@contextlib.contextmanager
def _temp_beside(path: Path) -> Iterator[Path]:
    """Temporary path beside ``path`` that keeps its suffix (FFmpeg picks the container by it)."""
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_gray_video(
    path: str | Path, frames: Iterable[np.ndarray], fps: float, codec: str = "ffv1"
) -> int:
    """Write uint8 [H, W] frames to ``path`` (container from its suffix); returns the count.

    The file appears under its final name only once complete.
    """
    import cv2

    path = Path(path)
    if codec not in CODECS:
        raise InputError(f"unknown codec {codec!r}, expected one of {sorted(CODECS)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = None
    n = 0
    with _temp_beside(path) as tmp:
        try:
            for frame in frames:
                if writer is None:
                    h, w = frame.shape[:2]
                    writer = cv2.VideoWriter(
                        str(tmp),
                        cv2.CAP_FFMPEG,
                        cv2.VideoWriter_fourcc(*CODECS[codec]),
                        fps,
                        (w, h),
                        [cv2.VIDEOWRITER_PROP_IS_COLOR, 0],
                    )
                    if not writer.isOpened():
                        raise InputError(
                            f"OpenCV cannot write codec {codec} into a {path.suffix} file", path
                        )
                writer.write(np.ascontiguousarray(frame, np.uint8))
                n += 1
        finally:
            if writer is not None:
                writer.release()
        _check_decodes(tmp, n, path)  # FFmpeg's failed writes (a full disk) are silent
    return n


def _check_decodes(tmp: Path, n: int, path: Path) -> None:
    """OutputError unless video ``tmp`` opens, announces ``n`` frames and its first decodes."""
    import cv2

    cap = cv2.VideoCapture(str(tmp), cv2.CAP_FFMPEG)
    try:
        ok = n == 0 or (
            cap.isOpened() and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == n and cap.read()[0]
        )
    finally:
        cap.release()
    if not ok:
        why = ": no space left on the device" if _nearly_full(tmp) else " (a full disk?)"
        raise OutputError(f"cannot write: the video did not come out decodable{why}", path)


def _nearly_full(p: Path) -> bool:
    """True when the filesystem holding ``p`` has less than 1 MB free."""
    return shutil.disk_usage(p.parent).free < 1 << 20
