"""``dronecap calibrate``: images or a video of a calibration board -> calib.json (+ a plot).

``dronecap calibrate left*.jpg --pattern chessboard --board 9x6 --square 0.025 -o calib.json``
finds the board in every image, calibrates with OpenCV and writes K, the distortion (OpenCV
order), the model, the image size, the RMS and per-view errors, the views used and rejected (with
reasons) and warnings. ``--video calib.mp4`` picks well-spread sharp frames first. The JSON is
what ``dronecap ingest --intrinsics`` reads (see docs/camera.md).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from dronecap import workspace
from dronecap.calibration.calibrate import MAX_VIEW_ERROR_PX, MODELS
from dronecap.calibration.targets import PATTERNS, SUBPIX_WINDOW
from dronecap.calibration.views import MAX_VIEWS
from dronecap.settings import Settings as Base
from dronecap.settings import output_setting, setting

OUTPUT = workspace.CALIBRATION  # default output, in the workspace


@dataclass(kw_only=True)
class Settings(Base):
    """Options of ``dronecap calibrate``."""

    images: list[str] = setting(
        factory=list, positional=True, help="calibration images: files, folders or globs"
    )
    video: str | None = setting(None, help="a video of the board instead of images")
    pattern: str = setting(choices=PATTERNS, help="board type")
    board: str = setting(
        help="WxH: inner corners (chessboard), squares (charuco) or markers (aruco-grid)"
    )
    square: float = setting(1.0, help="square side (board units)")
    marker: float | None = setting(None, help="marker side (charuco, aruco-grid)")
    gap: float | None = setting(None, help="space between markers (aruco-grid)")
    dictionary: str = setting("DICT_6X6_250", help="ArUco dictionary")
    model: str = setting("pinhole", choices=MODELS, help="lens model")
    subpix_window: int = setting(
        SUBPIX_WINDOW,
        help="chessboard corner refinement half-window (px); 0: 0.4 x the corner spacing, for "
        "small boards in small images",
    )
    max_views: int = setting(MAX_VIEWS, help="most views taken from a --video")
    max_view_error: float = setting(
        MAX_VIEW_ERROR_PX, help="reject views whose RMS error exceeds this (px) and 3x the median"
    )
    output: str | None = output_setting(
        "calibration JSON, or .yml/.xml for OpenCV's format", f"WORKDIR/{OUTPUT}"
    )
    plot: str | None = setting(
        None, help="also write a PNG of the corner coverage and per-view errors"
    )


def run(args: Settings) -> int:
    """Validate every option, find the board, calibrate, write the outputs."""
    from dronecap import workspace
    from dronecap.calibration.calibrate import MIN_VIEWS, calibrate, find_boards
    from dronecap.calibration.views import pick_video_views, read_images
    from dronecap.camera.files import write_calibration
    from dronecap.errors import InputError

    board = _board(args)
    if bool(args.images) == bool(args.video):
        raise InputError("give calibration images or --video FILE (one of them)")
    if args.max_views < MIN_VIEWS:
        raise InputError(f"--max-views must be at least {MIN_VIEWS}, got {args.max_views}")
    if not args.max_view_error > 0:
        raise InputError(f"--max-view-error must be positive, got {args.max_view_error}")
    if args.plot and not args.plot.lower().endswith(".png"):
        raise InputError("--plot must name a .png file", args.plot)
    out = workspace.resolve(args.workdir, args.output, OUTPUT)

    if args.video:
        views, rejected, size, decoded = pick_video_views(args.video, board, args.max_views)
        print(f"{args.video}: {decoded} frames, {len(views)} well-spread views of the board")
    else:
        from dronecap.progress import progress_bar

        images = progress_bar(read_images(args.images), desc="detect", unit="image")
        views, rejected, size = find_boards(images, board)
    cal = calibrate(views, size, board, args.model, rejected, args.max_view_error)
    write_calibration(out, cal.record())
    if args.plot:
        from dronecap.calibration.plot import plot_calibration

        plot_calibration(cal, views, args.plot)
    k = cal.camera
    for name, why in cal.rejected.items():
        if not why.startswith(("near-duplicate", "more than")):
            print(f"rejected {name}: {why}")
    for w in cal.warnings:
        print(f"dronecap calibrate: warning: {w}", file=sys.stderr)
    dist = ", ".join(f"{x:.4g}" for x in k.opencv_coeffs()[: 4 if k.is_fisheye else 5])
    print(
        f"{args.model} {k.width}x{k.height}: fx {k.fx:.2f}, fy {k.fy:.2f}, cx {k.cx:.2f}, "
        f"cy {k.cy:.2f}, distortion [{dist}], RMS {cal.rms:.3f} px from {len(cal.view_errors)} "
        f"views -> {out}"
    )
    return 0


def _board(args: Settings):
    """The Board of the options, or InputError naming the bad one."""
    from dronecap.calibration.targets import Board
    from dronecap.errors import InputError

    parts = args.board.lower().replace("×", "x").split("x")
    try:
        cols, rows = (int(v) for v in parts)
    except ValueError:
        raise InputError(f"--board must be WxH, e.g. 9x6, got {args.board!r}") from None
    board = Board(
        args.pattern,
        cols,
        rows,
        args.square,
        args.marker,
        args.gap,
        args.dictionary.upper(),
        args.subpix_window,
    )
    problems = board.problems()
    if problems:
        raise InputError(problems[0])
    return board
