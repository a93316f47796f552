"""What a run's steps worked on, in the GAP9 cost: the trainer's grid schedule, compaction's
trained share, the visual hull's share of the occupancy grid, and runs that predate them."""

from __future__ import annotations

import dataclasses
import json

import pytest

from dronecap.gap9 import arch
from dronecap.gap9.model import RunSamples, cost_report, deployed
from dronecap.gap9.search import Point, load_runs, to_target
from dronecap.nerf import occupancy
from dronecap.nerf.config import preset
from tests.gap9.conftest import TOY

# the default `scene-sized` preset as resolved on lego, in GAP9 tiles
LEGO = deployed(
    preset("scene-sized").replace(n_max=223, log2_hashmap=14, grid_res=64, march_steps=302)
)


@pytest.mark.parametrize(
    ("steps", "warmup", "every", "ramp"),
    [(10_000, 256, 16, 16), (1949, 256, 16, 4), (600, 0, 256, 16), (50, 64, 4, 1), (900, 1, 16, 4)],
)
def test_the_schedule_counted_is_the_trainers(steps, warmup, every, ramp):
    cfg = LEGO.replace(steps=steps, grid_warmup=warmup, grid_every=every, grid_ramp=ramp)
    grid = occupancy.GridConfig(res=cfg.grid_res, warmup=warmup, every=every, ramp=ramp)
    due = [s for s in range(steps) if occupancy.due(grid, s)]
    sched = arch.grid_schedule(cfg)
    assert sched.warmup_updates == sum(1 for s in due if s < warmup)
    assert sched.updates == len(due)


def test_the_trainers_schedule_updates_less_in_warm_up_than_the_fixed_rule():
    # Instant-NGP's interval grows from step 32 on: 76 updates in a 256-step warm-up, not 256
    paper_warmup = LEGO.replace(grid_warmup=256, grid_ramp=16)
    trainer = arch.grid_schedule(paper_warmup)
    fixed = arch.grid_schedule(paper_warmup, rule="fixed")
    assert (trainer.warmup_updates, fixed.warmup_updates) == (76, 256)
    assert trainer.steady_updates == fixed.steady_updates == 609  # every 16 from step 256 on
    # the default's warm-up is its first update, and its interval reaches 16 at step 64, not
    # 256: 40 fewer updates, all in the first 256 steps
    default = arch.grid_schedule(LEGO)
    assert (default.warmup_updates, default.updates) == (1, trainer.updates - 40)
    # the paper's run: every 256 steps, no warm-up -> 39 updates in 10k steps
    flown = preset("tiny-dronerf").replace(grid_every=256, grid_warmup=0)
    assert arch.grid_schedule(flown, rule="fixed").updates == 39


@pytest.mark.parametrize("counts", ["marched", "trained"])
def test_compaction_hand_count_on_the_toy(gap9, counts):
    # pre-pass per marched sample: hash 216 + density MLP 56 + ReLU 4 + exp 1 + alpha/T 6 = 283
    toy = TOY.replace(batch_counts=counts)
    assert sum(arch.prepass_ops_per_sample(toy).values()) == 283
    full = cost_report(toy, gap9, samples_per_pixel=2.0)["ops"]["step"]
    half = cost_report(toy, gap9, samples_per_pixel=2.0, run=RunSamples(0.5))["ops"]["step"]
    if counts == "marched":  # 8 samples marched, 4 of them trained on
        assert half["forward"] == pytest.approx(8 * (283 + 0.5 * 53))  # 336 - 283 = 53
        assert half["backward"] == pytest.approx(0.5 * full["backward"])
    else:  # 16 samples marched (the pre-pass on each), 8 trained on
        assert half["forward"] == pytest.approx(16 * 283 + 8 * 53)
        assert half["backward"] == pytest.approx(full["backward"])
    assert (half["loss"], half["optimizer"]) == (full["loss"], full["optimizer"])


def test_a_batch_of_trained_samples_costs_more_per_step_as_compaction_drops_more(gap9):
    """B counting the trained samples: a step marches B / f, so it gets dearer as f falls (the
    pre-pass), never below the uncompacted step; the memory (tiles) does not change."""
    reps = [cost_report(LEGO, gap9, run=RunSamples(f)) for f in (1.0, 0.7, 0.42)]
    steps = [r["latency"]["step"] for r in reps]
    assert steps[0] < steps[1] < steps[2] < 1.5 * steps[0]
    assert all(r["memory"] == reps[0]["memory"] for r in reps)


def test_a_smaller_trained_fraction_lowers_time_and_energy_never_memory(gap9):
    marched = LEGO.replace(batch_counts="marched")  # B counts the marched samples
    reps = [cost_report(marched, gap9, run=RunSamples(f)) for f in (1.0, 0.7, 0.42)]
    steps = [r["latency"]["step"] for r in reps]
    joules = [r["energy"]["run"] for r in reps]
    assert steps[0] > steps[1] > steps[2]
    assert joules[0] > joules[1] > joules[2]
    for r in reps[1:]:
        assert r["memory"] == reps[0]["memory"]  # tiles stay sized for every marched sample
        assert r["verdicts"] == reps[0]["verdicts"]
        assert r["l3_traffic"] == reps[0]["l3_traffic"]  # levels cross L3 whatever the count
        assert r["latency"]["render_frame"] == reps[0]["latency"]["render_frame"]
    # the pre-pass stays: at 0.42 a tile costs more than 0.42 of a full one
    kept, full = reps[2]["latency"], reps[0]["latency"]
    tile_share = (kept["forward_tile"] + kept["backward_tile"]) / (
        full["forward_tile"] + full["backward_tile"]
    )
    assert 0.42 < tile_share < 0.7


def test_the_hull_cuts_the_occupancy_time_by_its_share(gap9):
    box = cost_report(LEGO, gap9)["latency"]
    hull = cost_report(LEGO, gap9, run=RunSamples(hull_fraction=0.39))["latency"]
    assert hull["occupancy_run"] / box["occupancy_run"] == pytest.approx(0.39, rel=0.05)
    assert hull["occupancy_warmup_update"] < 0.42 * box["occupancy_warmup_update"]
    # the training steps themselves do not change
    assert hull["tile"] == box["tile"] and hull["adam_step"] == box["adam_step"]


def test_run_samples_from_metrics_old_and_new():
    assert RunSamples.from_metrics({"test": {"psnr": 27.0}}) == RunSamples(1.0, 1.0)
    doc = {"samples": {"marched": 1000, "trained": 450, "hull_fraction": 0.389}}
    assert RunSamples.from_metrics(doc) == RunSamples(0.45, 0.389)
    with pytest.raises(ValueError, match="trained_fraction"):
        RunSamples(0.0)
    with pytest.raises(ValueError, match="hull_fraction"):
        RunSamples(hull_fraction=1.5)


def test_runs_with_and_without_samples_load_and_cost(tmp_path):
    cfg = dataclasses.asdict(LEGO.replace(steps=3000, batch_counts="marched"))
    curve = [{"step": 1000, "psnr": 25.0}, {"step": 2000, "psnr": 27.0}]
    old = {"test": {"psnr": 27.5}, "config": cfg, "curve": curve}
    new = old | {"samples": {"marched": 100, "trained": 42, "hull_fraction": 0.39}}
    paths = []
    for name, doc in (("old", old), ("new", new)):
        (tmp_path / name).mkdir()
        paths.append(tmp_path / name / "metrics.json")
        paths[-1].write_text(json.dumps(doc))
    pts = load_runs(paths)
    assert pts[0].run == RunSamples() and pts[1].run == RunSamples(0.42, 0.39)
    rows = {r["label"]: r for r in to_target(pts, 26.94)}
    assert rows["old"]["steps"] == rows["new"]["steps"] == 2000
    assert rows["new"]["minutes"] < rows["old"]["minutes"]
    assert rows["new"]["joules"] < rows["old"]["joules"]
    # a point built by hand (a published row) is costed as before: neither compaction nor hull
    assert Point("p", LEGO, 27.0).run == RunSamples()
