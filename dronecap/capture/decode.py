"""Frame sources: a video file OpenCV can read (its wheel bundles FFmpeg), or a folder of images.

A source yields ``DecodedFrame`` records in order. Videos report the container's frame count and
rate so that a truncated recording is recognised (fewer frames decoded than announced); image
folders are sorted naturally (``img2.png`` before ``img10.png``) and timed at a given rate.
FFmpeg's own console messages are silenced while decoding: problems become one
:class:`InputError` line instead.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO, TypeVar

import numpy as np

from dronecap.errors import InputError
from dronecap.limits import check_frame_pixels, read_image

T = TypeVar("T")
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}


@dataclass
class SourceInfo:
    """What is known about a source before decoding it."""

    path: Path
    kind: str  # "video" or "images"
    width: int
    height: int
    fps: float  # frames per second (container rate, or the rate given for an image folder)
    expected_frames: int | None  # announced by the container; None when unknown
    codec: str  # FourCC of a video, or "images"


@dataclass
class DecodedFrame:
    """One source frame: ``image`` is uint8 [H, W] or [H, W, 3|4] BGR(A); None if unreadable."""

    index: int  # frame number in the source, from 0
    timestamp: float  # seconds from the start of the source
    image: np.ndarray | None
    name: str


def natural_key(name: str) -> list[object]:
    """Sort key that orders digit runs by value: ``f2`` < ``f10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


class VideoSource:
    """Decode a video file with OpenCV's FFmpeg backend."""

    def __init__(self, path: Path) -> None:
        import cv2

        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        self.path = path
        with silenced_native_stderr():
            cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        if not cap.isOpened():
            raise InputError(_unopenable_reason(path), path)
        self._cap = cap
        fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.info = SourceInfo(
            path=path,
            kind="video",
            width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            fps=fps if 0 < fps < 1000 else 30.0,
            expected_frames=count if count > 0 else None,
            codec="".join(chr((fourcc >> 8 * i) & 0xFF) for i in range(4)).strip("\x00") or "?",
        )
        check_frame_pixels(self.info.width, self.info.height, path)

    def frames(self) -> Iterator[DecodedFrame]:
        """Decode every frame in order; stops at the end or at the first undecodable frame."""
        import cv2

        cap, fps = self._cap, self.info.fps
        last_t = -1.0
        index = 0
        try:
            while True:
                with silenced_native_stderr():  # per call: never left redirected between frames
                    ok, image = cap.read()
                if not ok or image is None:
                    break
                t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                if not (t > last_t) or (index > 0 and t == 0.0):
                    t = index / fps  # container without usable timestamps
                last_t = t
                yield DecodedFrame(index, t, image, f"frame_{index:06d}")
                index += 1
        finally:
            cap.release()


class ImageFolderSource:
    """Read the images of a folder in natural order, timed at ``fps``.

    A file that does not decode is an :class:`InputError` naming it, unless ``skip_unreadable``
    (then it comes back with ``image=None``).
    """

    def __init__(self, path: Path, fps: float, skip_unreadable: bool = False) -> None:

        self.path = path
        self.skip_unreadable = skip_unreadable
        self.files = sorted(
            (p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
            key=lambda p: natural_key(p.name),
        )
        if not self.files:
            raise InputError(f"folder holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})", path)
        first = None
        for f in self.files:
            first = read_image(f)
            if first is not None:
                break
        if first is None:
            raise InputError(f"none of the {len(self.files)} images can be read", path)
        self.info = SourceInfo(
            path=path,
            kind="images",
            width=int(first.shape[1]),
            height=int(first.shape[0]),
            fps=fps,
            expected_frames=len(self.files),
            codec="images",
        )

    def frames(self) -> Iterator[DecodedFrame]:
        """Every image in natural order (unreadable ones as ``image=None`` when skipped)."""
        size = (self.info.height, self.info.width)
        for i, f in enumerate(self.files):
            image = read_image(f)
            if image is None and not self.skip_unreadable:
                raise InputError(
                    f"image {i + 1} of {len(self.files)} does not decode (damaged or not an "
                    "image); --skip-unreadable drops such frames",
                    f,
                )
            if image is not None and tuple(image.shape[:2]) != size:
                raise InputError(
                    f"is {image.shape[1]}x{image.shape[0]} but the folder's first image is "
                    f"{size[1]}x{size[0]}; all frames must share one size",
                    f,
                )
            yield DecodedFrame(i, i / self.info.fps, image, f.name)


def open_source(
    path: str | Path, fps: float = 30.0, skip_unreadable: bool = False
) -> VideoSource | ImageFolderSource:
    """Open a video file or an image folder; raise :class:`InputError` when it is neither."""
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", path)
    if path.is_dir():
        return ImageFolderSource(path, fps, skip_unreadable)
    if path.stat().st_size == 0:
        raise InputError("is an empty file, not a video", path)
    return VideoSource(path)


def _unopenable_reason(path: Path) -> str:
    with open(path, "rb") as fh:
        head = fh.read(12)
    if head[4:8] == b"ftyp":
        return (
            "MP4/MOV file without a readable index (moov atom): the recording was cut off "
            "before it was finalised, or the file is damaged; no frame can be decoded"
        )
    return "not a video file OpenCV/FFmpeg can read"


@contextlib.contextmanager
def silenced_native_stderr() -> Iterator[None]:
    """Send what native code (FFmpeg) prints on file descriptor 2 to /dev/null meanwhile.

    Python's ``sys.stderr`` object keeps working when it is not fd 2 (e.g. under pytest);
    progress bars use :func:`progress_stream` so they stay visible.
    """
    try:
        fd = sys.__stderr__.fileno() if sys.__stderr__ else 2
    except (OSError, ValueError):  # no real stderr (embedded interpreter)
        yield
        return
    with contextlib.suppress(Exception):
        sys.__stderr__.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


_PROGRESS: TextIO | None = None


def progress_stream() -> TextIO:
    """A text stream on a duplicate of the original stderr, unaffected by the silencing above."""
    global _PROGRESS
    if _PROGRESS is None:
        try:
            _PROGRESS = os.fdopen(os.dup(sys.__stderr__.fileno()), "w", buffering=1)
        except (OSError, ValueError, AttributeError):
            _PROGRESS = sys.stderr
    return _PROGRESS


def prefetch(frames: Iterator[T], depth: int = 16) -> Iterator[T]:
    """Run the iterator ``frames`` in a background thread (OpenCV releases the GIL while decoding).

    Decoding then overlaps with the per-frame processing of the consumer; errors raised by the
    producer are re-raised in the consumer.
    """
    q: queue.Queue[object] = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def put(item: object) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        close = getattr(frames, "close", None)
        try:
            for item in frames:
                if not put(item):
                    return
            put(done)
        except BaseException as err:  # handed to the consumer
            put(err)
        finally:
            if close is not None:
                close()  # release the decoder now, not at garbage collection

    worker = threading.Thread(target=produce, daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item  # type: ignore[misc]
    finally:
        stop.set()
        worker.join(timeout=5)
