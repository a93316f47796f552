"""Training to a budget: the plan, held-out checks and the stops, on hand-made step times."""

from __future__ import annotations

import pytest

from dronecap.nerf import budget
from dronecap.nerf.budget import BudgetConfig, BudgetState


def simulate(cfg: BudgetConfig, steps: int, dt_of_step) -> tuple[int, float, BudgetState]:
    """Run the budget logic over steps of known duration; returns (steps, seconds, state)."""
    state = budget.start(cfg, steps)
    step, seconds = 0, 0.0
    while not budget.finished(state, step):
        dt = dt_of_step(step)
        step, seconds = step + 1, seconds + dt
        budget.after_step(cfg, state, step, seconds, dt)
    return step, seconds, state


def test_no_budget_trains_the_fixed_step_count():
    step, _, state = simulate(BudgetConfig(), 1234, lambda s: 0.5)
    assert step == 1234 and state.planned_steps == 1234 and state.stop_reason is None


def test_time_budget_plans_the_steps_that_fit():
    # 10 ms per step in a 10 s budget: 1000 steps, whatever the preset's count
    step, seconds, state = simulate(BudgetConfig(time_budget_s=10.0), 10_000, lambda s: 0.01)
    assert abs(step - 1000) <= 1 and seconds <= 10.0 + 0.01
    assert state.planned_steps == step


def test_plan_follows_a_changing_step_time():
    # 20 ms during the 300 probe steps (6 s), then 10 ms: 300 + 4 s / 10 ms = 700 steps
    step, seconds, _ = simulate(
        BudgetConfig(time_budget_s=10.0), 10_000, lambda s: 0.02 if s < 300 else 0.01
    )
    assert abs(step - 700) <= 2 and seconds <= 10.0 + 0.02


def test_plan_is_made_before_the_budget_ends_with_few_preset_steps():
    # the preset says 100 steps, the budget affords 1000: the plan, not the preset, decides
    step, _, _ = simulate(BudgetConfig(time_budget_s=10.0), 100, lambda s: 0.01)
    assert abs(step - 1000) <= 1


def test_target_psnr_stops():
    cfg = BudgetConfig(target_psnr=25.0)
    state = budget.start(cfg, 1000)
    assert budget.record_check(cfg, state, 50, 1.0, 24.9) is None
    assert "target PSNR 25" in budget.record_check(cfg, state, 100, 2.0, 25.1)
    assert budget.finished(state, 100)
    assert [p["psnr"] for p in state.curve] == [24.9, 25.1]


def test_plateau_stops_when_the_last_checks_gain_too_little():
    cfg = BudgetConfig(plateau_db=0.1, plateau_checks=4)
    state = budget.start(cfg, 1000)
    psnrs = [20.0, 22.0, 23.0, 23.02, 23.03, 23.01, 23.04]
    reasons = [budget.record_check(cfg, state, 10 * i, i, p) for i, p in enumerate(psnrs)]
    # 5th check: best of the last 4 (23.03) vs 20.0; 6th: 23.03 vs 22.0;
    # 7th: 23.04 vs 23.0 -> +0.04 < 0.1 dB
    assert reasons[:6] == [None] * 6
    assert reasons[6].startswith("plateau: +0.040 dB")


def test_checks_every_tenth_of_the_plan_not_after_the_last_step():
    cfg = BudgetConfig()
    state = budget.start(cfg, 1000)
    due = [s for s in range(1, 1001) if budget.check_due(cfg, state, s)
           and budget.record_check(cfg, state, s, 0.0, 20.0) is None]  # fmt: skip
    assert due == list(range(100, 1000, 100))


@pytest.mark.parametrize("resumed_at", [0, 40, 48, 119])
def test_a_resumed_run_checks_at_the_steps_of_an_uninterrupted_one(resumed_at):
    # progress/step_NNNNNN.png names the checked steps: a run killed and resumed from a
    # checkpoint must write the same files as one that never stopped
    cfg = BudgetConfig()
    state = budget.start(cfg, 120, step=resumed_at)
    due = [s for s in range(resumed_at + 1, 121) if budget.check_due(cfg, state, s)
           and budget.record_check(cfg, state, s, 0.0, 20.0) is None]  # fmt: skip
    assert due == [s for s in range(12, 120, 12) if s > resumed_at]


@pytest.mark.parametrize(
    "cfg, words",
    [
        (BudgetConfig(time_budget_s=-1.0), "time budget"),
        (BudgetConfig(time_budget_s=float("nan")), "time budget"),
        (BudgetConfig(target_psnr=float("inf")), "target PSNR"),
        (BudgetConfig(plateau_db=-0.1), "plateau"),
        (BudgetConfig(plateau_checks=0), "plateau checks"),
        (BudgetConfig(target_psnr=25.0, check_views=0), "held-out checks"),
    ],
)
def test_bad_settings_are_named(cfg, words):
    assert any(words in p for p in cfg.problems())


def test_state_round_trips():
    cfg = BudgetConfig(time_budget_s=5.0)
    _, _, state = simulate(cfg, 10, lambda s: 0.01)
    assert BudgetState.from_dict(state.as_dict()) == state


def test_train_stops_at_a_target_and_records_its_curve(cube_h5, tmp_path, capsys):
    """A 1 dB target is met by the first held-out check (step 10 of 100: 10 %)."""
    import json

    from dronecap.cli import main

    run = tmp_path / "run"
    args = ["train", str(cube_h5), "--preset", "test", "--steps", "100", "--target-psnr", "1"]
    assert main([*args, "--out", str(run), "--no-progress", "--threads", "1"]) == 0
    assert "stopped early: target PSNR 1 dB reached" in capsys.readouterr().out
    m = json.loads((run / "metrics.json").read_text())
    assert m["steps"] == 10 and [p["step"] for p in m["curve"]] == [10]
    assert m["until"]["target_psnr"] == 1.0
    assert (run / "progress" / "step_000010.png").exists()  # the half-resolution preview


def test_fixed_steps_record_ten_checks(cube_h5, tmp_path):
    import json

    from dronecap.cli import main

    run = tmp_path / "run"
    args = ["train", str(cube_h5), "--preset", "test", "--steps", "40", "--out", str(run)]
    assert main([*args, "--no-progress", "--threads", "1"]) == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["steps"] == 40 and [p["step"] for p in m["curve"]] == list(range(4, 40, 4))
    assert m["until"]["stop_reason"] is None


@pytest.mark.parametrize(
    "option, words",
    [
        (["--time-budget", "-5"], "time budget"),
        (["--target-psnr", "nan"], "target PSNR"),
        (["--plateau-db", "-1"], "plateau"),
    ],
)
def test_bad_budget_options_are_one_line(cube_h5, tmp_path, capsys, option, words):
    from dronecap.cli import main

    out = tmp_path / "r"
    assert main(["train", str(cube_h5), *option, "--out", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err
    assert not out.exists()


def test_a_budget_that_is_not_a_number_is_refused_by_the_parser(cube_h5, tmp_path, capsys):
    """time_budget is typed (float): the CLI refuses text in one line, exit code 2."""
    from dronecap.cli import main

    out = tmp_path / "r"
    args = ["train", str(cube_h5), "--time-budget", "soon", "--out", str(out)]
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--time-budget" in err and "soon" in err
    assert not out.exists()


def test_time_budget_run_decays_less_unless_told(cube_h5, tmp_path):
    import json

    from dronecap.cli import main

    for extra, ratio in (([], 0.3), (["--lr-final-ratio", "0.05"], 0.05)):
        run = tmp_path / f"run{ratio}"
        args = ["train", str(cube_h5), "--preset", "test", "--time-budget", "0.5", *extra]
        assert main([*args, "--out", str(run), "--no-progress", "--threads", "1"]) == 0
        m = json.loads((run / "metrics.json").read_text())
        assert m["config"]["lr_final_ratio"] == ratio and m["until"]["time_budget_s"] == 0.5
