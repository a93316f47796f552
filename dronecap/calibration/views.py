"""Calibration views: images named on the command line, or well-spread sharp frames of a video.

A calibration video holds thousands of near-identical frames; calibrating on all of them is slow
and weights the poses the operator lingered on. :func:`pick_video_views` keeps the sharpest frame
(variance of the Laplacian) of each of ``CANDIDATES_PER_VIEW x max_views`` equal stretches of
the video (half a second each when the container does not say how long it is), finds the board
in those as it goes (only the corners are kept), drops the blurry ones, and then picks views
by farthest-point sampling on where the board's outline lands in the image (position, size and
tilt at once).
"""

from __future__ import annotations

import glob
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dronecap.calibration.calibrate import View, find_view
from dronecap.calibration.targets import Board
from dronecap.errors import InputError

MAX_VIEWS = 30  # default of the max_views setting: plenty for 9 intrinsics, still a quick solve
CANDIDATES_PER_VIEW = 4  # sharpest frame of each of 4 x max_views stretches is a candidate
BLUR_RATIO = 0.3  # a candidate sharper than this x the median sharpness is not blurry
MIN_SPREAD = 0.02  # outlines closer than this (mean corner distance / image diagonal) repeat


def read_images(specs: list[str]) -> Iterator[tuple[str, np.ndarray]]:
    """(name, uint8 [H, W] gray) of every image in ``specs`` (files, folders, glob patterns),
    in natural order within a folder or glob.

    Raises:
        InputError: a spec that matches nothing, or an image OpenCV cannot read.
    """
    import cv2

    from dronecap.capture.decode import IMAGE_SUFFIXES, natural_key

    paths: list[Path] = []
    for spec in specs:
        p = Path(spec)
        if p.is_dir():
            found = [f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES]
        elif p.exists():
            found = [p]
        else:
            found = [Path(f) for f in glob.glob(spec) if Path(f).suffix.lower() in IMAGE_SUFFIXES]
        if not found:
            raise InputError("no calibration images here", spec)
        paths += sorted(found, key=lambda f: natural_key(f.name))
    for path in paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise InputError("not an image OpenCV can read", path)
        yield str(path), gray


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of a uint8 [H, W] image (higher is sharper)."""
    import cv2

    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def pick_video_views(
    path: str | Path, board: Board, max_views: int = MAX_VIEWS, progress: bool = True
) -> tuple[list[View], dict[str, str], tuple[int, int], int]:
    """Choose up to ``max_views`` sharp, well-spread views of ``board`` in a video.

    Returns:
        (chosen views, rejected candidate -> reason, frame size (w, h), frames decoded).
        Views are named ``VIDEO#INDEX`` (frame number from 0).
    """
    from dronecap.capture.decode import open_source
    from dronecap.capture.framing import to_gray
    from dronecap.progress import progress_bar

    src = open_source(path)
    if src.info.kind != "video":
        raise InputError("video must be a video file (give images as the images setting)", path)
    name = Path(path).name
    expected = src.info.expected_frames or 0
    if expected:
        stretch = max(1, -(-expected // (CANDIDATES_PER_VIEW * max_views)))
    else:  # length unknown: two candidates per second of video
        stretch = max(1, round(src.info.fps / 2))
    views: list[View] = []
    rejected: dict[str, str] = {}
    scores: dict[str, float] = {}

    def consider(s: float, label: str, gray: np.ndarray) -> None:
        """Find the board in a candidate (only candidates are kept: no frames in memory)."""
        if find_view(board, label, gray, views, rejected):
            scores[label] = s

    best: tuple[float, str, np.ndarray] | None = None  # sharpest frame of the current stretch
    decoded, size = 0, (0, 0)
    bar = progress_bar(src.frames(), total=expected or None, desc="scan", unit="frame",
                       disable=None if progress else True)  # fmt: skip
    for frame in bar:
        decoded += 1
        if frame.image is None:
            continue
        gray = to_gray(frame.image)
        size = (gray.shape[1], gray.shape[0])
        s = sharpness(gray)
        if best is None or s > best[0]:
            best = (s, f"{name}#{frame.index}", gray)
        if (frame.index + 1) % stretch == 0:
            consider(*best)
            best = None
    if best is not None:
        consider(*best)
    if not size[0]:
        raise InputError("no decodable frame in the video", path)
    if views:
        med = float(np.median(list(scores.values())))
        for v in [v for v in views if scores[v.name] < BLUR_RATIO * med]:
            rejected[v.name] = f"blurry (sharpness {scores[v.name]:.0f}, median {med:.0f})"
        views = [v for v in views if v.name not in rejected]
    chosen, repeats = spread_views(views, size, max_views, [scores[v.name] for v in views])
    rejected.update(repeats)
    return chosen, rejected, size, decoded


def spread_views(
    views: list[View], size: tuple[int, int], max_views: int, scores: list[float]
) -> tuple[list[View], dict[str, str]]:
    """Farthest-point sampling of ``views`` on their board outlines, starting from the
    highest ``score``; stops at ``max_views`` or when every remaining view is within
    ``MIN_SPREAD`` of a chosen one. Returns (chosen in input order, left-out -> reason)."""
    if not views:
        return [], {}
    desc = np.stack([_outline(v, size) for v in views])  # [V, 4, 2], units of the diagonal
    chosen = [int(np.argmax(scores))]
    dist = np.linalg.norm(desc - desc[chosen[0]], axis=-1).mean(-1)
    nearest = np.zeros(len(views), int) + chosen[0]
    while len(chosen) < min(max_views, len(views)):
        i = int(np.argmax(dist))
        if dist[i] < MIN_SPREAD:
            break
        chosen.append(i)
        d = np.linalg.norm(desc - desc[i], axis=-1).mean(-1)
        nearest = np.where(d < dist, i, nearest)
        dist = np.minimum(dist, d)
    keep = sorted(chosen)
    out = {
        views[j].name: (
            f"near-duplicate of {views[nearest[j]].name}"
            if dist[j] < MIN_SPREAD
            else f"more than max_views {max_views} spread views"
        )
        for j in range(len(views))
        if j not in chosen
    }
    return [views[j] for j in keep], out


def _outline(view: View, size: tuple[int, int]) -> np.ndarray:
    """Image positions of the four corners of the detected part of the board, float [4, 2],
    divided by the image diagonal (via the board-to-image homography)."""
    import cv2

    obj = view.detection.object_points[:, :2].astype(np.float64)
    img = view.detection.image_points.astype(np.float64)
    h, _ = cv2.findHomography(obj, img)
    lo, hi = obj.min(0), obj.max(0)
    quad = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    if h is None:  # degenerate (collinear) detection: fall back to the points' bounding box
        ilo, ihi = img.min(0), img.max(0)
        pts = np.array([[ilo[0], ilo[1]], [ihi[0], ilo[1]], [ihi[0], ihi[1]], [ilo[0], ihi[1]]])
    else:
        pts = cv2.perspectiveTransform(quad.reshape(-1, 1, 2), h).reshape(4, 2)
    return pts / float(np.hypot(*size))
