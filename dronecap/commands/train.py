"""`dronecap train`: train Tiny-DroNeRF on a dataset into a run dir (resumable).

dronecap train [dataset.h5] [--preset tiny-dronerf] [--steps N] [--out RUN_DIR]
               [--set FIELD=VALUE ...] [--FIELD VALUE ...] [--no-resume] [--threads N]
"""

from __future__ import annotations

import argparse

from dronecap.cpu import add_threads_argument, use_torch_threads

HELP = "train Tiny-DroNeRF on a dataset -> run dir"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command (one per TrainConfig field, generated from the dataclass)."""
    from dronecap.nerf.config import add_config_arguments

    p.add_argument("dataset", nargs="?", help="dataset.h5 (default: WORKDIR/dataset.h5)")
    p.add_argument("--out", help="run dir (default: WORKDIR/runs/train)")
    p.add_argument(
        "--no-resume", action="store_true", help="start over even if a checkpoint exists"
    )
    add_threads_argument(p)
    p.add_argument(
        "--backend",
        default="auto",
        choices=("auto", "cpp", "torch", "compile"),
        help="hash-grid/marching implementation (auto: C++ kernels when they build)",
    )
    p.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_arguments(p)


def run(args: argparse.Namespace) -> int:
    """Train, evaluate, print the test metrics."""
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.nerf.config import config_from_args

    try:
        cfg = config_from_args(args)
    except (ValueError, KeyError, TypeError) as err:
        raise InputError(str(err).strip("'\"")) from None
    if cfg.steps < 0:
        raise InputError(f"steps must be >= 0, got {cfg.steps}")
    dataset = workspace.resolve(args.workdir, args.dataset, workspace.DATASET)
    out = workspace.resolve(args.workdir, args.out, workspace.TRAIN_RUN)
    from dronecap.nerf.trainer import train_run

    use_torch_threads(args.threads)
    m = train_run(
        dataset,
        cfg,
        out,
        resume=not args.no_resume,
        progress=not args.no_progress,
        checkpoint_every=max(1, args.checkpoint_every),
        backend=args.backend,
    )
    t = m["test"]
    print(
        f"{out}: {m['steps']} steps in {m['train_seconds']:.0f} s "
        f"({m['ms_per_step_median'] or 0:.1f} ms/step), test PSNR {t['psnr']:.2f} dB, "
        f"SSIM {t['ssim']:.3f} over {t['views']} views"
    )
    return 0
