"""`dronecap train`: train Tiny-DroNeRF on a dataset into a run dir (resumable), then ask the
GAP9 cost model for the run's cost.json.

dronecap train [dataset.h5] [--preset scene-sized] [--steps N] [--out RUN_DIR]
               [--time-budget S] [--target-psnr DB] [--plateau-db DB] [--budget-mb MB]
               [--set FIELD=VALUE ...] [--FIELD VALUE ...] [--no-resume | --resume-from RUN]
               [--no-eval] [--threads N]
"""

from __future__ import annotations

import argparse

from dronecap.cpu import add_threads_argument, check_threads, use_torch_threads

HELP = "train Tiny-DroNeRF on a dataset -> run dir"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the command (one per TrainConfig field, generated from the dataclass)."""
    from dronecap.nerf.backend import BACKENDS
    from dronecap.nerf.config import add_config_arguments

    p.add_argument("dataset", nargs="?", help="dataset.h5 (default: WORKDIR/dataset.h5)")
    p.add_argument("--out", help="run dir (default: WORKDIR/runs/train)")
    p.add_argument(
        "--no-resume", action="store_true", help="start over even if a checkpoint exists"
    )
    p.add_argument(
        "--resume-from",
        metavar="RUN",
        help="continue the model of another run folder (or checkpoint), even one trained on "
        "another dataset (with a warning)",
    )
    p.add_argument(
        "--no-eval", action="store_true", help="do not evaluate (a dataset without test views)"
    )
    add_threads_argument(p)
    p.add_argument(
        "--backend",
        default="auto",
        choices=BACKENDS,
        help="hash-grid/marching implementation (auto: C++ kernels when they build)",
    )
    p.add_argument("--checkpoint-every", default="500", help="steps between checkpoints")
    p.add_argument(
        "--time-budget",
        metavar="SECONDS",
        help="train for this many seconds: the step count and lr decay are planned from the "
        "measured step time (default: the configuration's fixed step count)",
    )
    p.add_argument("--target-psnr", metavar="DB", help="stop once held-out views reach this PSNR")
    p.add_argument(
        "--plateau-db",
        default="0",
        metavar="DB",
        help="stop when the held-out PSNR gained less than this over the last 4 checks "
        "(default 0: off)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_arguments(p)


def run(args: argparse.Namespace) -> int:
    """Check every option, train, evaluate, write cost.json, print the test metrics."""
    from dronecap import workspace
    from dronecap.errors import InputError
    from dronecap.nerf.config import config_from_args
    from dronecap.nerf.resolve import check_config

    try:
        cfg = config_from_args(args)
    except (ValueError, KeyError, TypeError) as err:
        raise InputError(str(err).strip("'\"")) from None
    check_config(cfg)
    check_threads(args.threads)
    try:
        every = int(args.checkpoint_every)
    except ValueError:
        every = 0
    if every < 1:
        raise InputError(
            f"--checkpoint-every takes a positive integer, got {args.checkpoint_every!r}"
        )
    if args.resume_from and args.no_resume:
        raise InputError("give --resume-from or --no-resume, not both")
    until = _until(args)
    given = {a.split("=", 1)[0].strip().replace("-", "_") for a in args.set}
    if until.time_budget_s and args.cfg_lr_final_ratio is None and "lr_final_ratio" not in given:
        from dronecap.nerf.budget import BUDGET_LR_FINAL_RATIO

        cfg = cfg.replace(lr_final_ratio=BUDGET_LR_FINAL_RATIO)  # a short schedule decays less
    dataset = workspace.resolve(args.workdir, args.dataset, workspace.DATASET)
    out = workspace.resolve(args.workdir, args.out, workspace.TRAIN_RUN)
    from dronecap.commands.cost import write_run_cost
    from dronecap.gap9.model import cost_report
    from dronecap.nerf.run_dir import train_run

    def gap9_bytes(c):  # modelled GAP9 memory (Table II accounting) for the sizing's budget
        return cost_report(c)["memory"]["untiled"]["total"]

    use_torch_threads(args.threads)
    m = train_run(
        dataset,
        cfg,
        out,
        resume=not args.no_resume,
        progress=not args.no_progress,
        checkpoint_every=every,
        backend=args.backend,
        evaluate=not args.no_eval,
        resume_from=args.resume_from,
        memory_fn=gap9_bytes,
        until=until,
    )
    write_run_cost(out)
    done = (
        f"{out}: {m['steps']} steps in {m['train_seconds']:.0f} s "
        f"({m['ms_per_step_median'] or 0:.1f} ms/step)"
    )
    if m["until"]["stop_reason"]:
        done += f", stopped early: {m['until']['stop_reason']}"
    t = m["test"]
    if t is None:
        print(f"{done}, not evaluated (--no-eval)")
    else:
        print(f"{done}, test PSNR {t['psnr']:.2f} dB, SSIM {t['ssim']:.3f} over {t['views']} views")
    return 0


def _until(args: argparse.Namespace):
    """The BudgetConfig of --time-budget/--target-psnr/--plateau-db (InputError when bad)."""
    from dronecap.errors import InputError
    from dronecap.nerf.budget import BudgetConfig

    def number(text, option):
        if text is None:
            return None
        try:
            return float(text)
        except ValueError:
            raise InputError(f"{option} takes a number, got {text!r}") from None

    until = BudgetConfig(
        time_budget_s=number(args.time_budget, "--time-budget"),
        target_psnr=number(args.target_psnr, "--target-psnr"),
        plateau_db=number(args.plateau_db, "--plateau-db"),
    )
    bad = until.problems()
    if bad:
        raise InputError("; ".join(bad))
    return until
