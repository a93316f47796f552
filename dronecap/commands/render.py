"""`dronecap render`: render a trained run's test views or an orbit to PNGs (and an MP4).

dronecap render [RUN_DIR] [--orbit N] [--mp4] [--dataset dataset.h5] [--out DIR]
"""

from __future__ import annotations

import argparse

from dronecap.cpu import add_threads_argument, check_threads, use_torch_threads

HELP = "render views (test poses or an orbit) of a trained run"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("run_dir", nargs="?", help="run dir (default: WORKDIR/runs/train)")
    p.add_argument("--orbit", type=int, metavar="N", help="render N views on a circle instead")
    p.add_argument("--mp4", action="store_true", help="also write the frames as video.mp4")
    p.add_argument("--fps", type=int, default=24, help="video frame rate")
    p.add_argument("--dataset", help="dataset.h5 (default: the one the run was trained on)")
    p.add_argument("--out", help="output folder (default: RUN_DIR/render)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_threads_argument(p)


def run(args: argparse.Namespace) -> int:
    """Render and write the images."""
    from pathlib import Path

    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.nerf.evaluate import test_views
    from dronecap.nerf.outputs import orbit_poses, write_mp4, write_png
    from dronecap.nerf.run_dir import open_run
    from dronecap.progress import progress_bar

    check_threads(args.threads)
    if args.orbit is not None and args.orbit < 1:
        raise InputError(f"--orbit takes a positive number of views, got {args.orbit}")
    if not 1 <= args.fps <= 240:
        raise InputError(f"--fps takes 1..240 frames per second, got {args.fps}")
    run_dir = workspace.resolve(args.workdir, args.run_dir, workspace.TRAIN_RUN)
    use_torch_threads(args.threads)
    trainer, ds = open_run(run_dir, args.dataset)
    out = Path(args.out) if args.out else run_dir / "render"
    if args.orbit is not None:
        poses = orbit_poses(ds.poses, trainer.scene.aabb.mean(0), args.orbit)
        names = [f"orbit_{i:03d}" for i in range(args.orbit)]
    else:
        idx = test_views(ds)
        if idx.size == 0:
            raise InputError("dataset has no test or val views; use --orbit N", ds_path(args))
        poses = ds.poses[idx]
        names = [f"test_{i:03d}" for i in idx]
    frames = []
    for pose, name in progress_bar(
        list(zip(poses, names, strict=True)), desc="render", unit="view", disable=args.no_progress
    ):
        img = trainer.render(pose, ds.intrinsics)
        write_png(out / f"{name}.png", img)
        frames.append(img)
    if args.mp4:
        write_mp4(out / "video.mp4", frames, args.fps)
    print(f"{out}: {len(frames)} views" + (" + video.mp4" if args.mp4 else ""))
    return 0


def ds_path(args: argparse.Namespace) -> str:
    """The dataset path as the user gave it (for messages)."""
    return args.dataset or "the run's dataset"
