"""Calibration targets: chessboard, ChArUco and ArUco grid boards, and finding them in an image.

Board sizes follow OpenCV's conventions:

- ``chessboard``: ``cols x rows`` INNER corners (OpenCV's 9x6 sample board), ``square`` the side
  of a square; corners are found with ``cv2.findChessboardCorners`` and refined with
  ``cv2.cornerSubPix`` (OpenCV's recipe: half-window 11 px; ``subpix_window=0`` sizes it to
  0.4 x the corner spacing, which small boards in small images need: a window reaching past
  the middle of a square pulls corners towards their neighbours), falling back to
  ``cv2.findChessboardCornersSB``;
- ``charuco``: ``cols x rows`` SQUARES, ``square`` and ``marker`` sides, an ArUco dictionary;
  ``cv2.aruco.CharucoDetector`` finds the markers and interpolates the chessboard corners;
- ``aruco-grid``: ``cols x rows`` MARKERS of side ``marker`` separated by ``gap``; the four
  corners of every marker found by ``cv2.aruco.ArucoDetector`` (sub-pixel refined).

Object points are in the board's units (whatever ``square``/``marker`` are given in: the
intrinsics do not depend on them), on the plane z = 0. Image points are in dronecap's pixel
convention (centre of pixel (u, v) at (u + 0.5, v + 0.5), as COLMAP and the datasets use):
OpenCV's corner finders put pixel centres at integers, so :data:`OPENCV_TO_DRONECAP_PX` is added
to what they return, and a calibration's cx, cy come out 0.5 px larger than OpenCV's own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATTERNS = ("chessboard", "charuco", "aruco-grid")
SUBPIX_WINDOW = 11  # cornerSubPix half-window (px), OpenCV's calibration sample
AUTO_WINDOW_FRACTION = 0.4  # subpix_window=0: half-window = this x the corner spacing
SUBPIX_CRITERIA = (3, 30, 0.001)  # COUNT | EPS, 30 iterations, 0.001 px (the sample's)
OPENCV_TO_DRONECAP_PX = 0.5  # OpenCV pixel centres at integers, dronecap at +0.5
MIN_POINTS = 6  # fewer points do not constrain a view's pose and the intrinsics together
MIN_FRACTION = 0.25  # ChArUco / ArUco grid: a view must show this fraction of the board's points


@dataclass(frozen=True)
class Detection:
    """Board points found in one image: ``image_points`` float32 [N, 2] (pixels, centres at
    integer + 0.5) and ``object_points`` float32 [N, 3] (board units, z = 0)."""

    image_points: np.ndarray
    object_points: np.ndarray
    spacing: float = float("inf")  # chessboard: least distance between neighbour corners (px)
    window: int = 0  # chessboard: cornerSubPix half-window used (px)

    @property
    def n(self) -> int:
        """Number of points."""
        return len(self.image_points)


@dataclass(frozen=True)
class Board:
    """A calibration target (see the module docstring for what ``cols x rows`` counts)."""

    pattern: str
    cols: int
    rows: int
    square: float = 1.0  # side of a chessboard square (chessboard, charuco)
    marker: float | None = None  # side of a marker (charuco, aruco-grid)
    gap: float | None = None  # space between markers (aruco-grid)
    dictionary: str = "DICT_6X6_250"  # ArUco dictionary (charuco, aruco-grid)
    subpix_window: int = SUBPIX_WINDOW  # chessboard corner refinement half-window; 0: auto

    def problems(self) -> list[str]:
        """What is wrong with this board definition (empty when usable)."""
        import cv2

        out = []
        if self.pattern not in PATTERNS:
            out.append(f"pattern must be one of {', '.join(PATTERNS)}, found {self.pattern!r}")
            return out
        least = 3 if self.pattern == "chessboard" else 2
        if self.cols < least or self.rows < least:
            out.append(f"a {self.pattern} board needs at least {least}x{least}")
        if self.subpix_window < 0:
            out.append(f"subpix_window must be 0 (auto) or positive, found {self.subpix_window}")
        if self.pattern != "aruco-grid" and not self.square > 0:
            out.append(f"square must be positive, found {self.square}")
        if self.pattern == "charuco" and not (self.marker and 0 < self.marker < self.square):
            out.append(f"marker must be positive and smaller than square, found {self.marker}")
        if self.pattern == "aruco-grid":
            if not (self.marker and self.marker > 0):
                out.append(f"marker must be positive, found {self.marker}")
            if not (self.gap and self.gap > 0):
                out.append(f"gap must be positive, found {self.gap}")
        if self.pattern != "chessboard":
            if not hasattr(cv2.aruco, self.dictionary):
                out.append(f"unknown ArUco dictionary {self.dictionary!r}")
            elif (
                self.markers
                > cv2.aruco.getPredefinedDictionary(
                    getattr(cv2.aruco, self.dictionary)
                ).bytesList.shape[0]
            ):
                out.append(f"{self.dictionary} has fewer markers than the board needs")
        return out

    @property
    def markers(self) -> int:
        """Number of ArUco markers on the board (0 for a chessboard)."""
        if self.pattern == "charuco":
            return (self.cols * self.rows) // 2
        return self.cols * self.rows if self.pattern == "aruco-grid" else 0

    @property
    def points(self) -> int:
        """Number of points the whole board shows."""
        if self.pattern == "chessboard":
            return self.cols * self.rows
        if self.pattern == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        return 4 * self.cols * self.rows

    @property
    def min_points(self) -> int:
        """Fewest points a view must show to be used (a chessboard is all or nothing)."""
        if self.pattern == "chessboard":
            return self.points
        return max(MIN_POINTS, int(np.ceil(MIN_FRACTION * self.points)))

    def detect(self, gray: np.ndarray) -> Detection | None:
        """Find the board in a uint8 [H, W] image; None when nothing of it is found."""
        if self.pattern == "chessboard":
            return self._chessboard(gray)
        return self._aruco(gray)

    def record(self) -> dict[str, object]:
        """JSON-able description (stored in the calibration file)."""
        out: dict[str, object] = {"pattern": self.pattern, "board": [self.cols, self.rows]}
        if self.pattern != "aruco-grid":
            out["square"] = self.square
        if self.pattern == "chessboard":
            out["subpix_window"] = self.subpix_window
        if self.pattern != "chessboard":
            out.update(marker=self.marker, dictionary=self.dictionary)
        if self.pattern == "aruco-grid":
            out["gap"] = self.gap
        return out

    # -- detectors ------------------------------------------------------------------------------
    def _chessboard(self, gray: np.ndarray) -> Detection | None:
        import cv2

        size = (self.cols, self.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, size, flags=flags)
        win = 0
        if found:
            spacing = _spacing(corners, size)
            win = self.subpix_window or max(2, int(AUTO_WINDOW_FRACTION * spacing))
            corners = cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), SUBPIX_CRITERIA)
        else:
            found, corners = cv2.findChessboardCornersSB(gray, size)
            if not found:
                return None
            spacing = _spacing(corners, size)
        grid = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2) * self.square
        obj = np.c_[grid, np.zeros(len(grid))].astype(np.float32)
        return Detection(_to_dronecap(corners), obj, spacing, win)

    def _aruco(self, gray: np.ndarray) -> Detection | None:
        board, detector = _opencv_board(self)
        if self.pattern == "charuco":
            corners, ids, _, _ = detector.detectBoard(gray)
        else:
            corners, ids, _ = detector.detectMarkers(gray)
        if ids is None or len(ids) == 0:
            return None
        obj, img = board.matchImagePoints(corners, ids)
        if obj is None or len(obj) == 0:
            return None
        return Detection(_to_dronecap(img), obj.reshape(-1, 3).astype(np.float32))


def _spacing(corners: np.ndarray, size: tuple[int, int]) -> float:
    """Least distance (px) between neighbouring chessboard corners (cols x rows grid)."""
    c = corners.reshape(size[1], size[0], 2).astype(np.float64)
    along = np.linalg.norm(np.diff(c, axis=1), axis=-1).min()
    across = np.linalg.norm(np.diff(c, axis=0), axis=-1).min()
    return float(min(along, across))


def _to_dronecap(points: np.ndarray) -> np.ndarray:
    """OpenCV corner coordinates (any shape [..., 2]) -> float32 [N, 2], centres at +0.5."""
    return (points.reshape(-1, 2).astype(np.float64) + OPENCV_TO_DRONECAP_PX).astype(np.float32)


_CACHE: dict[Board, tuple[object, object]] = {}


def _opencv_board(board: Board) -> tuple:
    """(cv2.aruco board, detector) of a ChArUco or ArUco-grid board, built once."""
    import cv2

    if board not in _CACHE:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
        size = (board.cols, board.rows)
        if board.pattern == "charuco":
            b = cv2.aruco.CharucoBoard(size, board.square, board.marker, dictionary)
            det = cv2.aruco.CharucoDetector(b)
        else:
            b = cv2.aruco.GridBoard(size, board.marker, board.gap, dictionary)
            params = cv2.aruco.DetectorParameters()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            det = cv2.aruco.ArucoDetector(dictionary, params)
        _CACHE[board] = (b, det)
    return _CACHE[board]
