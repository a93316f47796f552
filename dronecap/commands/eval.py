"""`dronecap eval`: re-evaluate a trained run on all its test views (PSNR/SSIM, scikit-image).

dronecap eval [RUN_DIR] [--dataset dataset.h5]
"""

from __future__ import annotations

import argparse

from dronecap.cpu import add_threads_argument, use_torch_threads

HELP = "re-evaluate a trained run on its test views (PSNR/SSIM)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("run_dir", nargs="?", help="run dir (default: WORKDIR/runs/train)")
    p.add_argument("--dataset", help="dataset.h5 (default: the one the run was trained on)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_threads_argument(p)


def run(args: argparse.Namespace) -> int:
    """Evaluate and update metrics.json."""
    from dronecap import workspace
    from dronecap.nerf.runs import open_run, update_metrics

    run_dir = workspace.resolve(args.workdir, args.run_dir, workspace.TRAIN_RUN)
    use_torch_threads(args.threads)
    trainer, ds = open_run(run_dir, args.dataset)
    from dronecap.nerf.trainer import evaluate_run

    m = update_metrics(run_dir, evaluate_run(trainer, ds, run_dir, not args.no_progress))
    t = m["test"]
    print(f"{run_dir}: test PSNR {t['psnr']:.2f} dB, SSIM {t['ssim']:.3f} over {t['views']} views")
    return 0
