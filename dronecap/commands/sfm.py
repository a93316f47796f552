"""``dronecap sfm``: recover camera poses with COLMAP, normalise and bound -> posed.h5."""

from __future__ import annotations

import argparse
from dataclasses import fields

HELP = "recover camera poses with COLMAP (pycolmap), normalise and bound the scene -> posed.h5"

# CLI flag -> SfmOptions field, for the settings worth exposing
_FLAGS = {
    "--max-features": ("max_features", int, "SIFT keypoints kept per frame"),
    "--first-octave": ("first_octave", int, "-1 upsamples tiny frames before SIFT, 0 does not"),
    "--matcher": ("matcher", str, "auto | sequential | exhaustive"),
    "--exhaustive-below": ("exhaustive_below", int, "auto: exhaustive below this many frames"),
    "--overlap": ("overlap", int, "sequential: frames matched after each frame"),
    "--loop-period": ("loop_period", int, "loop detection: query every this-many-th frame"),
    "--loop-images": ("loop_num_images", int, "loop detection: frames retrieved per query"),
    "--min-registration": ("min_registration", float, "fail below this registered fraction"),
    "--seed": ("seed", int, "mapper random seed"),
    "--init-trials": ("init_trials", int, "2: also map from COLMAP's initial pair; keep best"),
    "--threads": ("num_threads", int, "COLMAP threads (-1: all cores)"),
    "--camera": (
        "camera",
        str,
        "fixed | refine | estimate; auto: fixed when frames.h5 has a calibrated camera",
    ),
    "--init-max-gap": ("init_max_gap", int, "initial pair: at most this many frames apart"),
    "--retry-below": ("retry_below", float, "retry with remedies below this registered fraction"),
    "--retry-budget": ("retry_budget", float, "seconds after which no new retry starts"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``dronecap sfm`` (defaults from dronecap.sfm.options.SfmOptions)."""
    p.add_argument("--frames", help="input frames.h5 (default: WORKDIR/frames.h5)")
    p.add_argument("-o", "--output", help="output posed.h5 (default: WORKDIR/posed.h5)")
    p.add_argument("--sfm-dir", help="model, PLY and report folder (default: WORKDIR/sfm)")
    p.add_argument(
        "--gt",
        help="ground truth to measure accuracy against: the simulator's flight.json/poses.json, "
        "or a TUM trajectory (matched to the frames by timestamp, within 20 ms)",
    )
    p.add_argument(
        "--camera-from",
        help="posed.h5 of an earlier reconstruction of the same drone: use its camera",
    )
    p.add_argument(
        "--clahe",
        dest="clahe",
        action="store_true",
        default=None,
        help="contrast-normalise frames before SIFT (low-contrast, vignetted footage)",
    )
    p.add_argument(
        "--prior-fallback",
        dest="prior_fallback",
        action="store_true",
        default=None,
        help="frames that fail to register keep their telemetry prior pose in posed.h5",
    )
    for flag, (name, typ, text) in _FLAGS.items():
        p.add_argument(flag, dest=name, type=typ, default=None, help=text)
    p.add_argument(
        "--quadratic-overlap",
        dest="quadratic_overlap",
        action="store_true",
        default=None,
        help="sequential: pair frame i with i+2^k (COLMAP default) instead of i+1..i+overlap",
    )
    p.add_argument(
        "--no-loop-detection",
        dest="loop_detection",
        action="store_false",
        default=None,
        help="sequential: no loop pairs from the flight's visual index",
    )
    p.add_argument(
        "--no-extend",
        dest="extend",
        action="store_false",
        default=None,
        help="do not resume mapping from the largest model to absorb the others",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar and no printed report")


def run(args: argparse.Namespace) -> int:
    """Run the stage; 0 on success (InputError -> exit 1 via the CLI)."""
    from pathlib import Path

    from dronecap import workspace
    from dronecap.sfm.options import SfmOptions
    from dronecap.sfm.pipeline import run_sfm

    given = {
        f.name: getattr(args, f.name)
        for f in fields(SfmOptions)
        if getattr(args, f.name, None) is not None
    }
    opts = SfmOptions(**given)
    report = run_sfm(
        frames_path=workspace.resolve(args.workdir, args.frames, workspace.FRAMES),
        posed_path=workspace.resolve(args.workdir, args.output, workspace.POSED),
        sfm_dir=workspace.resolve(args.workdir, args.sfm_dir, workspace.SFM_DIR),
        opts=opts,
        gt_path=Path(args.gt) if args.gt else None,
        progress=not args.quiet,
        camera_from=Path(args.camera_from) if args.camera_from else None,
    )
    return 0 if report["status"] == "ok" else 1
