"""`dronecap train`: train Tiny-DroNeRF on a dataset into a run dir (resumable), then ask the
GAP9 cost model for the run's cost.json.

dronecap train [dataset.h5] [--preset scene-sized] [--steps N] [--out RUN_DIR]
               [--time-budget S] [--target-psnr DB] [--plateau-db DB] [--budget-mb MB]
               [--set FIELD=VALUE ...] [--FIELD VALUE ...] [--no-resume | --resume-from RUN]
               [--no-eval] [--threads N]

Every ``TrainConfig`` field is an option (``--steps 3000``) except the ones the dataset decides
(``nerf.config.DATA_FIELDS``: resolution, channels, train images).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from dronecap.nerf.backend import BACKENDS
from dronecap.nerf.config import DATA_FIELDS, DEFAULT_PRESET, PRESETS, TrainConfig, parse_field
from dronecap.stage import flatten, setting
from dronecap.stage_common import ProgressSettings, TorchSettings

CONFIG_FIELDS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.name not in DATA_FIELDS)


@dataclass(kw_only=True)
class Settings(TorchSettings, ProgressSettings):
    """Options of ``dronecap train``."""

    dataset: str | None = setting(
        None, positional=True, help="dataset.h5 (default: WORKDIR/dataset.h5)"
    )
    out: str | None = setting(None, help="run dir (default: WORKDIR/runs/train)")
    no_resume: bool = setting(False, help="start over even if a checkpoint exists")
    resume_from: str | None = setting(
        None,
        metavar="RUN",
        help="continue the model of another run folder (or checkpoint), even one trained on "
        "another dataset (with a warning)",
    )
    no_eval: bool = setting(False, help="do not evaluate (a dataset without test views)")
    backend: str = setting(
        "auto",
        choices=BACKENDS,
        help="hash-grid/marching implementation (auto: C++ kernels when they build)",
    )
    checkpoint_every: str = setting("500", help="steps between checkpoints")
    time_budget: str | None = setting(
        None,
        metavar="SECONDS",
        help="train for this many seconds: the step count and lr decay are planned from the "
        "measured step time (default: the configuration's fixed step count)",
    )
    target_psnr: str | None = setting(
        None, metavar="DB", help="stop once held-out views reach this PSNR"
    )
    plateau_db: str = setting(
        "0",
        metavar="DB",
        help="stop when the held-out PSNR gained less than this over the last 4 checks "
        "(default 0: off)",
    )
    preset: str = setting(DEFAULT_PRESET, help=f"named configuration: {', '.join(PRESETS)}")
    set: list[str] = setting(
        factory=list,
        repeat=True,
        metavar="FIELD=VALUE",
        help="override any configuration field (repeatable)",
    )
    config: dict[str, Any] = flatten(
        TrainConfig,
        only=CONFIG_FIELDS,
        parse=parse_field,
        help=lambda f: f"{f.name} (preset value otherwise)",
        group="configuration fields (override the preset)",
    )


def run(s: Settings) -> int:
    """Check every option, train, evaluate, write cost.json, print the test metrics."""
    from dronecap import workspace
    from dronecap.cpu import check_threads, use_torch_threads
    from dronecap.errors import InputError
    from dronecap.nerf.config import config_from_overrides
    from dronecap.nerf.resolve import check_config

    given = {a.split("=", 1)[0].strip().replace("-", "_") for a in s.set} | set(s.config)
    decided = sorted(given & set(DATA_FIELDS))
    if decided:
        raise InputError(f"{decided[0]} is the dataset's (resolved from it), not a setting")
    try:
        cfg = config_from_overrides(s.preset, s.set, s.config)
    except (ValueError, KeyError, TypeError) as err:
        raise InputError(str(err).strip("'\"")) from None
    check_config(cfg)
    check_threads(s.threads)
    try:
        every = int(s.checkpoint_every)
    except ValueError:
        every = 0
    if every < 1:
        raise InputError(f"--checkpoint-every takes a positive integer, got {s.checkpoint_every!r}")
    if s.resume_from and s.no_resume:
        raise InputError("give --resume-from or --no-resume, not both")
    until = _until(s)
    if until.time_budget_s and "lr_final_ratio" not in given:
        from dronecap.nerf.budget import BUDGET_LR_FINAL_RATIO

        cfg = cfg.replace(lr_final_ratio=BUDGET_LR_FINAL_RATIO)  # a short schedule decays less
    dataset = workspace.resolve(s.workdir, s.dataset, workspace.DATASET)
    out = workspace.resolve(s.workdir, s.out, workspace.TRAIN_RUN)
    from dronecap.commands.cost import write_run_cost
    from dronecap.gap9.model import memory_bytes
    from dronecap.nerf.run_dir import train_run

    use_torch_threads(s.threads)
    m = train_run(
        dataset,
        cfg,
        out,
        resume=not s.no_resume,
        progress=not s.no_progress,
        checkpoint_every=every,
        backend=s.backend,
        evaluate=not s.no_eval,
        resume_from=s.resume_from,
        memory_fn=memory_bytes,
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
        from dronecap.nerf.evaluate import scores_line

        print(f"{done}, {scores_line(t)}")
    return 0


def _until(s: Settings):
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
        time_budget_s=number(s.time_budget, "--time-budget"),
        target_psnr=number(s.target_psnr, "--target-psnr"),
        plateau_db=number(s.plateau_db, "--plateau-db"),
    )
    bad = until.problems()
    if bad:
        raise InputError("; ".join(bad))
    return until
