"""Camera calibration from views of a board: OpenCV's calibrateCamera / fisheye.calibrate with
view rejection and warnings about what the views leave unconstrained.

:func:`find_boards` detects the board in every image (rejecting views without it or with too few
corners); :func:`calibrate` solves, drops views whose reprojection error is far above the others
(once), and reports per-view RMS errors, the standard deviations OpenCV estimates for the
intrinsics, the image coverage and warnings. The pinhole recipe is OpenCV's own (default flags,
5 distortion coefficients ``k1, k2, p1, p2, k3``); ``model="fisheye"`` uses ``cv2.fisheye``
(equidistant, ``k1..k4``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dronecap.calibration.targets import Board, Detection
from dronecap.camera.model import Camera
from dronecap.errors import InputError

MODELS = ("pinhole", "fisheye")
MIN_VIEWS = 3  # fewer views of a plane leave focal length and distortion unconstrained
REJECT_FACTOR = 3.0  # a view is rejected when its RMS error exceeds this x the median ...
MAX_VIEW_ERROR_PX = 2.0  # ... and this many pixels (default of the max_view_error setting)
RMS_WARN_PX = 1.0  # a calibration with a larger RMS error is suspect
COVERAGE_GRID = 5  # the image is split in 5x5 cells; the border ones should see corners:
BORDER_REGIONS = {  # region -> its cells (row, column) in that grid
    "top-left corner": [(0, 0)],
    "top edge": [(0, 1), (0, 2), (0, 3)],
    "top-right corner": [(0, 4)],
    "left edge": [(1, 0), (2, 0), (3, 0)],
    "right edge": [(1, 4), (2, 4), (3, 4)],
    "bottom-left corner": [(4, 0)],
    "bottom edge": [(4, 1), (4, 2), (4, 3)],
    "bottom-right corner": [(4, 4)],
}
COVERAGE_CELLS = 10  # coverage fraction: share of a 10x10 grid of cells holding a corner
STD_RATIO = 0.5  # a distortion term whose std exceeds half its size (and STD_FLOOR) ...
STD_FLOOR = 0.1  # ... is reported as poorly constrained
DIST_NAMES = {"pinhole": ("k1", "k2", "p1", "p2", "k3"), "fisheye": ("k1", "k2", "k3", "k4")}


@dataclass(frozen=True)
class View:
    """One image in which the board was found."""

    name: str
    detection: Detection


@dataclass
class Calibration:
    """The result of :func:`calibrate`."""

    camera: Camera
    rms: float  # RMS reprojection error over all points of the used views (px)
    view_errors: dict[str, float]  # used view -> its RMS reprojection error (px)
    rejected: dict[str, str]  # view -> why it was not used
    board: Board
    std: dict[str, float] = field(default_factory=dict)  # std of fx, fy, cx, cy, k1... (pinhole)
    coverage: float = 0.0  # fraction of the image's 10x10 cells holding a corner
    warnings: list[str] = field(default_factory=list)

    def record(self) -> dict[str, Any]:
        """The calibration JSON (see :func:`dronecap.camera.files.calibration_record`)."""
        import cv2

        from dronecap.camera.files import calibration_record

        return calibration_record(
            self.camera,
            rms=self.rms,
            views_used=list(self.view_errors),
            view_errors=self.view_errors,
            rejected=self.rejected,
            std=self.std,
            coverage=self.coverage,
            warnings=self.warnings,
            target=self.board.record(),
            opencv=cv2.__version__,
        )


def find_boards(
    images: Iterable[tuple[str, np.ndarray]], board: Board
) -> tuple[list[View], dict[str, str], tuple[int, int]]:
    """Detect ``board`` in every (name, uint8 [H, W] gray image).

    Returns:
        (views with enough points, rejected name -> reason, image size (w, h)).

    Raises:
        InputError: no image, or images of different sizes.
    """
    views: list[View] = []
    rejected: dict[str, str] = {}
    size: tuple[int, int] | None = None
    first = ""
    for name, gray in images:
        h, w = gray.shape[:2]
        if size is None:
            size, first = (w, h), name
        elif (w, h) != size:
            raise InputError(
                f"image is {w}x{h} but {first} is {size[0]}x{size[1]}: all calibration views "
                "must come from the same camera mode",
                name,
            )
        find_view(board, name, gray, views, rejected)
    if size is None:
        raise InputError("no calibration images given")
    return views, rejected, size


def find_view(
    board: Board, name: str, gray: np.ndarray, views: list[View], rejected: dict[str, str]
) -> bool:
    """Detect ``board`` in one uint8 [H, W] gray image: True when it is a view (appended to
    ``views``), False when it is not (``rejected[name]`` says why)."""
    det = board.detect(gray)
    if det is None:
        rejected[name] = "board not found"
    elif det.n < board.min_points:
        rejected[name] = f"too few corners ({det.n} of {board.points}, need {board.min_points})"
    else:
        views.append(View(name, det))
        return True
    return False


def calibrate(
    views: list[View],
    size: tuple[int, int],
    board: Board,
    model: str = "pinhole",
    rejected: dict[str, str] | None = None,
    max_view_error: float = MAX_VIEW_ERROR_PX,
) -> Calibration:
    """Calibrate from the views of :func:`find_boards` for ``size`` (w, h) images.

    Views whose RMS error exceeds ``REJECT_FACTOR`` x the median and ``max_view_error`` (px)
    are rejected once and the camera solved again without them.

    Raises:
        InputError: fewer than ``MIN_VIEWS`` views, or OpenCV cannot solve.
    """
    if model not in MODELS:
        raise InputError(f"model must be one of {', '.join(MODELS)}, found {model!r}")
    rejected = dict(rejected or {})
    _check_count(views, rejected, board)
    cam, errors, std = _solve(views, size, model)
    med = float(np.median(list(errors.values())))
    limit = max(REJECT_FACTOR * med, max_view_error)
    bad = {n: e for n, e in errors.items() if e > limit}
    if bad and len(views) - len(bad) >= MIN_VIEWS:
        for n, e in bad.items():
            rejected[n] = f"large error ({e:.2f} px RMS, median {med:.2f} px)"
        views = [v for v in views if v.name not in bad]
        cam, errors, std = _solve(views, size, model)
    n_pts = np.array([v.detection.n for v in views])
    err = np.array([errors[v.name] for v in views])
    rms = float(np.sqrt((err**2 * n_pts).sum() / n_pts.sum()))
    points = np.concatenate([v.detection.image_points for v in views])
    result = Calibration(cam, rms, errors, rejected, board, std, _coverage(points, size))
    result.warnings = _warnings(result, points, model, {v.name: v.detection for v in views})
    return result


def _check_count(views: list[View], rejected: dict[str, str], board: Board) -> None:
    total = len(views) + len(rejected)
    what = f"{board.pattern} {board.cols}x{board.rows}"
    if not views:
        raise InputError(
            f"no {what} board found in any of the {total} images (check the pattern, board "
            "and, for ArUco boards, dictionary settings)"
        )
    if len(views) < MIN_VIEWS:
        raise InputError(
            f"the {what} board was found in only {len(views)} of {total} images; calibration "
            f"needs at least {MIN_VIEWS} views from different angles"
        )


def _solve(
    views: list[View], size: tuple[int, int], model: str
) -> tuple[Camera, dict[str, float], dict[str, float]]:
    """(camera, per-view RMS errors, std of the intrinsics) from OpenCV."""
    import cv2

    obj = [v.detection.object_points for v in views]
    img = [v.detection.image_points for v in views]
    try:
        if model == "fisheye":
            return _solve_fisheye(views, size)
        _, k, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(obj, img, size, None, None)
    except cv2.error as err:
        raise InputError(
            f"OpenCV could not calibrate from these views: {_cv_message(err)}"
        ) from None
    cam = Camera.from_opencv(k, dist, size[0], size[1])
    names = ("fx", "fy", "cx", "cy", *DIST_NAMES["pinhole"])
    errors = {v.name: float(e) for v, e in zip(views, per_view.ravel(), strict=True)}
    return cam, errors, {n: float(s) for n, s in zip(names, std.ravel(), strict=False)}


def _solve_fisheye(
    views: list[View], size: tuple[int, int]
) -> tuple[Camera, dict[str, float], dict[str, float]]:
    import cv2

    # cv2.fisheye wants each view as a [1, N, 3] / [1, N, 2] float64 array
    obj = [v.detection.object_points.reshape(1, -1, 3).astype(np.float64) for v in views]
    img = [v.detection.image_points.reshape(1, -1, 2).astype(np.float64) for v in views]
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW  # OpenCV 5: cv2.CALIB_*
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    _, k, d, rvecs, tvecs = cv2.fisheye.calibrate(
        obj, img, size, None, None, flags=flags, criteria=crit
    )
    errors = {}
    for v, o, i, r, t in zip(views, obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.fisheye.projectPoints(o, r, t, k, d)
        errors[v.name] = float(
            np.sqrt(((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2).sum(-1).mean())
        )
    return Camera.from_opencv(k, d, size[0], size[1], fisheye=True), errors, {}


def _coverage(points: np.ndarray, size: tuple[int, int]) -> float:
    """Share of the COVERAGE_CELLS x COVERAGE_CELLS cells of the image holding a corner."""
    cells = _cells(points, size, COVERAGE_CELLS)
    return len(set(cells.tolist())) / COVERAGE_CELLS**2


def _cells(points: np.ndarray, size: tuple[int, int], n: int) -> np.ndarray:
    """Row-major cell index in an n x n grid over the image of every point [N, 2] -> int [N]."""
    ix = np.clip((points[:, 0] / size[0] * n).astype(int), 0, n - 1)
    iy = np.clip((points[:, 1] / size[1] * n).astype(int), 0, n - 1)
    return iy * n + ix


def _warnings(
    cal: Calibration, points: np.ndarray, model: str, views: dict[str, Detection]
) -> list[str]:
    out = []
    n = COVERAGE_GRID
    seen = set(_cells(points, (cal.camera.width, cal.camera.height), n).tolist())
    empty = [
        name
        for name, cells in BORDER_REGIONS.items()
        if not any(r * n + c in seen for r, c in cells)
    ]
    if empty:
        out.append(
            f"no board corner near the image's {', '.join(empty)} (outer {100 // n}% of the "
            "image): the distortion there is extrapolated; add views with the board there"
        )
    names = DIST_NAMES[model]
    values = dict(zip(names, (*cal.camera.opencv_coeffs(), 0.0), strict=False))  # k3 may be 0
    loose = [
        f"{n} = {values[n]:.3g} +- {cal.std[n]:.2g}"
        for n in names
        if n in cal.std and cal.std[n] > max(STD_RATIO * abs(values[n]), STD_FLOOR)
    ]
    if loose:
        out.append(
            f"distortion poorly constrained ({'; '.join(loose)}): add views that tilt the "
            "board and reach the image corners"
        )
    tight = [n for n, v in views.items() if v.window and 2 * v.window >= v.spacing]
    if tight:
        out.append(
            f"in {len(tight)} views the corners are closer (down to "
            f"{min(views[n].spacing for n in tight):.0f} px) than the corner refinement window "
            "is wide: use subpix_window 0 (sized to the board) or bigger squares"
        )
    if cal.rms > RMS_WARN_PX:
        out.append(
            f"RMS reprojection error {cal.rms:.2f} px is high (blur, a bent board, or the wrong "
            "board size)"
        )
    return out


def _cv_message(err: Exception) -> str:
    """The readable part of an OpenCV error message."""
    text = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
    return text.split(") ", 1)[-1][:160]
