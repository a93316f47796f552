"""`dronecap eval`: score a trained run on the test views of a dataset (PSNR/SSIM, scikit-image)
into RUN_DIR/eval_<dataset stem>.json (the training record, metrics.json, is never touched).

dronecap eval [RUN_DIR] [--dataset dataset.h5]
"""

from __future__ import annotations

import argparse

from dronecap.cpu import add_threads_argument, check_threads, use_torch_threads

HELP = "score a trained run on a dataset's test views -> RUN_DIR/eval_<dataset>.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command."""
    p.add_argument("run_dir", nargs="?", help="run dir (default: WORKDIR/runs/train)")
    p.add_argument("--dataset", help="dataset.h5 (default: the one the run was trained on)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_threads_argument(p)


def run(args: argparse.Namespace) -> int:
    """Evaluate and write the dataset's eval file."""
    from dronecap import workspace
    from dronecap.nerf.run_dir import eval_run

    check_threads(args.threads)
    run_dir = workspace.resolve(args.workdir, args.run_dir, workspace.TRAIN_RUN)
    use_torch_threads(args.threads)
    out, rec = eval_run(run_dir, args.dataset, not args.no_progress)
    t = rec["test"]
    print(f"{out}: test PSNR {t['psnr']:.2f} dB, SSIM {t['ssim']:.3f} over {t['views']} views")
    return 0
