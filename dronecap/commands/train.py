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
from dronecap.settings import ProgressSettings, TorchSettings, flatten, input_setting, setting

CONFIG_FIELDS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.name not in DATA_FIELDS)


@dataclass(kw_only=True)
class Settings(TorchSettings, ProgressSettings):
    """Options of ``dronecap train``."""

    dataset: str | None = input_setting("dataset.h5", "WORKDIR/dataset.h5")
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
    checkpoint_every: int = setting(500, minimum=1, help="steps between checkpoints")
    time_budget: float | None = setting(
        None,
        metavar="SECONDS",
        help="train for this many seconds: the step count and lr decay are planned from the "
        "measured step time (default: the configuration's fixed step count)",
    )  # checked by BudgetConfig.problems
    target_psnr: float | None = setting(
        None, metavar="DB", help="stop once held-out views reach this PSNR"
    )
    plateau_db: float = setting(
        0.0,
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
    if s.resume_from and s.no_resume:
        raise InputError("give --resume-from or --no-resume, not both")
    until = _until(s)
    if until.time_budget_s and "lr_final_ratio" not in given:
        from dronecap.nerf.budget import BUDGET_LR_FINAL_RATIO

        cfg = cfg.replace(lr_final_ratio=BUDGET_LR_FINAL_RATIO)  # a short schedule decays less
    dataset = workspace.resolve(s.workdir, s.dataset, workspace.DATASET)
    out = workspace.resolve(s.workdir, s.out, workspace.TRAIN_RUN)
    from dronecap.gap9.model import RunSamples, cost_report, deployed, memory_bytes
    from dronecap.nerf.run_dir import COST, read_resolved, train_run, write_json

    use_torch_threads(s.threads)
    m = train_run(
        dataset,
        cfg,
        out,
        resume=not s.no_resume,
        progress=not s.no_progress,
        checkpoint_every=s.checkpoint_every,
        backend=s.backend,
        evaluate=not s.no_eval,
        resume_from=s.resume_from,
        memory_fn=memory_bytes,
        until=until,
    )
    # the run's GAP9 cost, priced on the steps trained and the samples they trained on
    # (run.json, metrics: the NeRF core never imports the cost model); the same report
    # `dronecap cost RUN_DIR` gives with its defaults
    samples = RunSamples.from_metrics(m)
    write_json(out / COST, cost_report(deployed(read_resolved(out).config), run=samples))
    done = (
        f"{out}: {m['steps']} steps in {m['train_seconds']:.0f} s "
        f"(median step {m['ms_per_step_median'] or 0:.1f} ms)"
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
    """The BudgetConfig of the time_budget/target_psnr/plateau_db settings (InputError naming
    the setting when one is out of range)."""
    from dronecap.errors import InputError
    from dronecap.nerf.budget import BudgetConfig

    until = BudgetConfig(
        time_budget_s=s.time_budget, target_psnr=s.target_psnr, plateau_db=s.plateau_db
    )
    bad = until.problems()
    if bad:
        raise InputError("; ".join(bad))
    return until
