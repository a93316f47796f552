"""Training to a budget: a time budget, a target PSNR and a plateau stop, as config + state.

Without any of them a run trains its fixed step count (reproducible). With
``time_budget_s`` the step count is *planned* from the measured step time: every
:data:`REPLAN_FRACTION` of the budget the plan becomes ``step + remaining seconds / recent
seconds per step``, and the trainer's learning-rate decay follows the plan, so the run ends
its schedule (lr at its final value) when the budget is spent instead of being cut short.
Training seconds are the time spent in optimizer steps (held-out checks and the final
evaluation are not counted; both are reported).

Held-out checks render ``check_views`` views (the validation split when the dataset has one,
else the test split) every :data:`CHECK_FRACTION` of the planned steps, at full resolution, and
record (step, seconds, PSNR): the run's PSNR-vs-time curve. A check may stop the run: the
target PSNR reached, or a plateau (the best PSNR of the last ``plateau_checks`` checks is less
than ``plateau_db`` above the best before them).

Pure functions over :class:`BudgetState` (saved in the checkpoint as a dict), so a resumed
run continues the same plan.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from dronecap.errors import InputError

from .config import TrainConfig

REPLAN_FRACTION = 0.05  # re-plan the step count every 5 % of the time budget
CHECK_FRACTION = 0.1  # a held-out check every 10 % of the planned steps (10 curve points)
RECENT_STEPS = 200  # step times the plan is made from (the latest ones)
PROBE_STEPS = 300  # steps before the first plan (the occupancy warm-up makes them slower)
# lr_final_ratio of a time-budgeted run unless the user sets one: lego, 60 s on one thread
# (~1.8k steps), 27.50 dB with 0.3 against 26.09 with the 10k-step schedule's 0.03
# (benchmarks/results/time_to_quality.md); longer budgets not measured
BUDGET_LR_FINAL_RATIO = 0.3


@dataclass(frozen=True)
class BudgetConfig:
    """When training stops (all None/0: the fixed step count of the TrainConfig).

    time_budget_s: training seconds to plan the schedule for (> 0), or None.
    target_psnr: stop once a held-out check reaches this PSNR (dB), or None.
    plateau_db: stop when the held-out PSNR gained less than this over the last
        ``plateau_checks`` checks (0: no plateau stop).
    plateau_checks: checks the plateau is judged over (>= 1).
    check_views: held-out views rendered per check (0: no checks, no curve).
    """

    time_budget_s: float | None = None
    target_psnr: float | None = None
    plateau_db: float = 0.0
    plateau_checks: int = 4
    check_views: int = 3

    def problems(self) -> list[str]:
        """Why the settings are unusable (empty when they are fine)."""
        out = []
        if self.time_budget_s is not None and not (
            math.isfinite(self.time_budget_s) and self.time_budget_s > 0
        ):
            out.append(
                f"time budget must be a positive number of seconds, got {self.time_budget_s}"
            )
        if self.target_psnr is not None and not (
            math.isfinite(self.target_psnr) and 0 < self.target_psnr < 100
        ):
            out.append(f"target PSNR must be in (0, 100) dB, got {self.target_psnr}")
        if not (math.isfinite(self.plateau_db) and self.plateau_db >= 0):
            out.append(f"plateau must be >= 0 dB, got {self.plateau_db}")
        if self.plateau_checks < 1:
            out.append(f"plateau checks must be >= 1, got {self.plateau_checks}")
        if self.check_views < 0:
            out.append(f"check views must be >= 0, got {self.check_views}")
        needs_checks = self.target_psnr is not None or self.plateau_db > 0
        if needs_checks and self.check_views == 0:
            out.append("a target PSNR or a plateau stop needs held-out checks (check views > 0)")
        return out


@dataclass
class BudgetState:
    """Progress against the budget.

    planned_steps: the step count the schedule runs to (the TrainConfig's without a time
    budget); next_plan_s: training seconds of the next re-plan; next_check: step of the next
    held-out check; step_seconds: recent step durations (s); curve: held-out checks
    [{"step", "seconds", "psnr"}]; stop_reason: why the run stopped early, or None.
    """

    planned_steps: int
    next_plan_s: float = 0.0
    next_check: int = 0
    step_seconds: list[float] = field(default_factory=list)
    curve: list[dict] = field(default_factory=list)
    stop_reason: str | None = None

    def as_dict(self) -> dict:
        """JSON-able copy (for the checkpoint and metrics)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> BudgetState:
        """Inverse of :meth:`as_dict`."""
        return cls(**d)


def held_out_views(split: np.ndarray | None, n: int) -> np.ndarray:
    """Up to ``n`` frame indices spread over the validation split (split 1), else over the
    test split (2); empty without a split."""
    if split is None or n <= 0:
        return np.zeros(0, np.int64)
    pool = np.flatnonzero(split == 1)
    pool = pool if pool.size else np.flatnonzero(split == 2)
    if pool.size == 0:
        return pool
    return np.unique(pool[np.linspace(0, pool.size - 1, min(n, pool.size)).astype(np.int64)])


def start(cfg: BudgetConfig, steps: int, step: int = 0, seconds: float = 0.0) -> BudgetState:
    """State of a run at ``step``; ``steps`` is the TrainConfig's count, which a time-budgeted
    run follows (at least PROBE_STEPS more) until its first plan after PROBE_STEPS steps."""
    planned = max(steps, step + PROBE_STEPS + 1) if cfg.time_budget_s else steps
    state = BudgetState(planned_steps=planned)
    state.next_plan_s = seconds
    interval = check_interval(state)  # on the same grid of steps as an uninterrupted run
    state.next_check = (step // interval + 1) * interval
    return state


def check_interval(state: BudgetState) -> int:
    """Steps between held-out checks: CHECK_FRACTION of the plan (at least 1)."""
    return max(1, round(CHECK_FRACTION * state.planned_steps))


def after_step(cfg: BudgetConfig, state: BudgetState, step: int, seconds: float, dt: float) -> None:
    """Account one finished optimizer step (``step`` done, ``seconds`` of training so far,
    ``dt`` its duration) and re-plan the step count when due (in place)."""
    state.step_seconds.append(dt)
    del state.step_seconds[:-RECENT_STEPS]
    budget = cfg.time_budget_s
    if budget is None:
        return
    if seconds >= budget:
        state.planned_steps = step
        return
    if step >= PROBE_STEPS and seconds >= state.next_plan_s:
        per_step = sorted(state.step_seconds)[len(state.step_seconds) // 2]
        state.planned_steps = step + max(1, int((budget - seconds) / max(per_step, 1e-6)))
        state.next_plan_s = seconds + REPLAN_FRACTION * budget
        state.next_check = min(state.next_check, step + check_interval(state))


def finished(state: BudgetState, step: int) -> bool:
    """Whether training stops before step ``step + 1``."""
    return step >= state.planned_steps or state.stop_reason is not None


def check_due(cfg: BudgetConfig, state: BudgetState, step: int) -> bool:
    """Whether a held-out check runs after step ``step`` (never after the last planned one:
    the final evaluation covers it)."""
    return cfg.check_views > 0 and step >= state.next_check and step < state.planned_steps


def record_check(
    cfg: BudgetConfig, state: BudgetState, step: int, seconds: float, psnr: float
) -> str | None:
    """Add a held-out check to the curve; returns (and stores) the stop reason, if any."""
    state.curve.append({"step": step, "seconds": seconds, "psnr": psnr})
    state.next_check = step + check_interval(state)
    if cfg.target_psnr is not None and psnr >= cfg.target_psnr:
        state.stop_reason = (
            f"target PSNR {cfg.target_psnr:g} dB reached on held-out views ({psnr:.2f} dB)"
        )
    elif cfg.plateau_db > 0 and len(state.curve) > cfg.plateau_checks:
        before = max(p["psnr"] for p in state.curve[: -cfg.plateau_checks])
        recent = max(p["psnr"] for p in state.curve[-cfg.plateau_checks :])
        if recent - before < cfg.plateau_db:
            state.stop_reason = (
                f"plateau: +{recent - before:.3f} dB over the last {cfg.plateau_checks} checks "
                f"(< {cfg.plateau_db:g} dB)"
            )
    return state.stop_reason


def learning_rate(cfg: TrainConfig, step: int, lr_steps: int) -> float:
    """The model's learning rate at ``step`` of a run whose decay spans ``lr_steps`` steps
    (a time budget re-plans ``lr_steps``)."""
    if cfg.lr_schedule == "constant":
        return cfg.lr
    if cfg.lr_schedule == "exp":
        return cfg.lr * cfg.lr_final_ratio ** min(step / max(lr_steps, 1), 1.0)
    raise InputError(f"unknown lr_schedule {cfg.lr_schedule!r}: use 'exp' or 'constant'")
