"""``dronecap simulate``: render a synthetic nano-drone flight (video + ground-truth JSON)."""

from __future__ import annotations

import argparse
import time

HELP = "render a synthetic nano-drone flight video with ground truth"
SCENES = ("corridor", "orbit")
CODECS = ("ffv1", "mjpg", "mp4v")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("--scene", default="corridor", choices=SCENES, help="scene (default: corridor)")
    p.add_argument(
        "-o",
        "--output",
        help="video file (default: WORKDIR/flight.mp4); ground truth goes beside it as .json",
    )
    p.add_argument("--frames", type=int, default=600, help="frames at 30 Hz (default: 600)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument(
        "--codec",
        default="ffv1",
        choices=CODECS,
        help="ffv1 = lossless (default, best for SIFT); mjpg / mp4v = smaller, lossy",
    )


def run(args: argparse.Namespace) -> int:
    """Render the flight and print where it went."""
    from dronecap import workspace
    from dronecap.simulator.simulate import simulate

    out = workspace.resolve(args.workdir, args.output, "flight.mp4")
    t0 = time.perf_counter()
    video, gt = simulate(args.scene, out, frames=args.frames, seed=args.seed, codec=args.codec)
    dt = time.perf_counter() - t0
    print(
        f"rendered {args.frames} frames of '{args.scene}' (seed {args.seed}) in {dt:.1f} s "
        f"({args.frames / dt:.0f} frames/s) -> {video}, ground truth {gt}"
    )
    return 0
