"""Steps resolved once: a run that stops elsewhere than the steps asked (a time budget, a
target PSNR) records the steps it trained in run.json, metrics.json, the checkpoint, cost.json
and what ``dronecap cost RUN_DIR`` prints, and the cost prices those steps."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from dronecap.cli import main


def _steps_everywhere(run: Path, capsys) -> dict[str, int]:
    """The step count of each output of a finished run folder (and of `dronecap cost RUN`)."""
    from dronecap.nerf.trainer import Trainer

    capsys.readouterr()
    assert main(["cost", str(run), "--json", str(run / "cost_again.json")]) == 0
    printed = re.search(r"training \((\d+) steps\)", capsys.readouterr().out)
    assert printed, "dronecap cost prints the steps it prices"
    metrics = json.loads((run / "metrics.json").read_text())
    return {
        "trained": metrics["steps"],
        "metrics.json config": metrics["config"]["steps"],
        "run.json": json.loads((run / "run.json").read_text())["config"]["steps"],
        "checkpoint": Trainer.load(run / "checkpoint.pt").cfg.steps,
        "cost.json": json.loads((run / "cost.json").read_text())["config"]["steps"],
        "dronecap cost": int(printed.group(1)),
    }


def test_an_early_stop_records_the_steps_it_trained(cube_h5, tmp_path, capsys):
    """A 1 dB target stops at the first check (step 10 of 100): every output says 10, and the
    GAP9 training time is that of 10 steps (a tenth of the 100 asked)."""
    run = tmp_path / "run"
    args = ["train", str(cube_h5), "--preset", "test", "--steps", "100", "--target-psnr", "1"]
    assert main([*args, "--out", str(run), "--no-progress", "--threads", "1"]) == 0
    steps = _steps_everywhere(run, capsys)
    assert set(steps.values()) == {10}, steps
    cost = json.loads((run / "cost.json").read_text())
    assert cost["latency"]["train"] == pytest.approx(10 * cost["latency"]["step"], rel=0.05)
    reasons = json.loads((run / "run.json").read_text())["reasons"]
    assert "target PSNR" in reasons["steps"]


@pytest.mark.data
def test_a_time_budget_on_lego_records_the_steps_it_trained(lego_dir, tmp_path, capsys):
    """`--time-budget` on the real lego scene (imported with import-blender, 40 px to stay
    fast): the run plans its own step count; all outputs agree on the steps trained, which
    are not the preset's."""
    h5 = tmp_path / "lego.h5"
    assert main(["-q", "import-blender", str(lego_dir), "-o", str(h5), "--resolution", "40"]) == 0
    run = tmp_path / "run"
    args = ["train", str(h5), "--preset", "test", "--time-budget", "3", "--no-eval"]
    assert main([*args, "--out", str(run), "--no-progress", "--threads", "1"]) == 0
    steps = _steps_everywhere(run, capsys)
    assert len(set(steps.values())) == 1, steps
    from dronecap.nerf.config import preset

    assert steps["trained"] != preset("test").steps
