"""`dronecap cost`: report, --table2, --search with and without measured runs, bad inputs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from dronecap.cli import main
from dronecap.gap9.search import Budget, Point, choose, pareto_front, search
from dronecap.nerf.config import apply_sets, config_from_dict, preset


def _metrics(run: Path, name: str, psnr: float) -> Path:
    run.mkdir(parents=True)
    f = run / "metrics.json"
    f.write_text(json.dumps({"psnr": psnr, "config": dataclasses.asdict(preset(name))}))
    return f


def test_report_preset_writes_json(tmp_path, capsys):
    assert main(["cost", "--workdir", str(tmp_path), "--preset", "b4k-t11"]) == 0
    out = capsys.readouterr().out
    assert "L2 peak" in out and "wrote" in out
    rep = json.loads((tmp_path / "cost.json").read_text())
    assert rep["config"]["batch_samples"] == 4096 and rep["config"]["log2_hashmap"] == 11


def _run_json(run: Path, cfg) -> None:
    """A run folder's run.json holding ``cfg`` as its resolved configuration."""
    import numpy as np

    from dronecap.nerf.resolve import Resolved, Scene

    run.mkdir(parents=True)
    scene = Scene(np.array([[-1.0, -1, -1], [1, 1, 1]]), 3.0, 200.0, 1, (0.0,))
    doc = {"dataset": "gone.h5"} | Resolved(cfg, scene, {"n_max": "test"}).to_dict()
    (run / "run.json").write_text(json.dumps(doc))


def test_report_run_dir_and_set(tmp_path):
    # the resolved values (auto-sized n_max 223, gray, 120 px, 37 images) are what is costed
    cfg = preset("tiny-dronerf-sized").replace(
        n_max=223, channels=1, resolution=120, train_images=37
    )
    _run_json(tmp_path / "run", cfg)
    args = ["cost", str(tmp_path / "run"), "--set", "log2_hashmap=12", "--set", "grid_res=64"]
    assert main(args) == 0
    rep = json.loads((tmp_path / "run" / "cost.json").read_text())
    assert rep["config"]["log2_hashmap"] == 12 and rep["config"]["grid_res"] == 64
    assert rep["counts"]["grid_cells"] == 64**3
    assert rep["config"]["n_max"] == 223 and rep["config"]["channels"] == 1
    assert rep["config"]["resolution"] == 120 and rep["assumptions"]["n_images"] == 37


@pytest.mark.parametrize(
    "argv",
    [
        ["--set", "nope=1"],
        ["--set", "batch_samples=lots"],
        ["--preset", "no-such-preset"],
        ["--platform", "missing.yaml"],
        ["--search"],
        ["--images", "-5"],
        ["--images", "0"],
        ["--spp", "0"],
        ["--spp", "nan"],
        ["--top", "0"],
        ["--set", "lr=nan"],
        ["--set", "batch_samples=0"],
        ["--set", "precision=fp8"],
        ["--platform", "{tmp}/fast.yaml"],
        ["--platform", "{tmp}/negative.yaml"],
        ["--platform", "{tmp}/broken.yaml"],
    ],
)
def test_bad_inputs_are_one_line_errors(tmp_path, capsys, argv):
    (tmp_path / "fast.yaml").write_text("clock_hz: fast\n")
    (tmp_path / "negative.yaml").write_text("numerics:\n  act_bytes: -2\n")
    (tmp_path / "broken.yaml").write_text("clock_hz: [1,\n")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(["cost", "--workdir", str(tmp_path), *argv]) == 1
    err = capsys.readouterr().err
    assert err.startswith("dronecap cost: error:") and err.count("\n") == 1
    assert not (tmp_path / "cost.json").exists()


def test_a_budget_that_is_not_a_size_is_refused_by_the_parser(tmp_path, capsys):
    """budget_l3 is typed (bytes, parsed once): the CLI refuses text in one line, exit 2."""
    with pytest.raises(SystemExit) as stop:
        main(["cost", "--workdir", str(tmp_path), "--search", "--budget-l3", "32 parsecs"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--budget-l3" in err and "unknown unit 'parsecs'" in err


def test_run_dir_without_config(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["cost", str(tmp_path / "empty")]) == 1
    assert "no run.json" in capsys.readouterr().err


def test_old_run_dir_without_its_dataset_gets_one_line(tmp_path, capsys):
    """A run.json from before resolved configs (config + n_max beside it) whose dataset is
    gone cannot say what was trained: one clear line, no report."""
    run = tmp_path / "old"
    run.mkdir()
    old = {"dataset": str(tmp_path / "gone.h5"), "config": dataclasses.asdict(preset("test"))}
    (run / "run.json").write_text(json.dumps(old | {"n_max": 223}))
    assert main(["cost", str(run)]) == 1
    err = capsys.readouterr().err
    assert "older dronecap" in err and err.count("\n") == 1
    assert not (run / "cost.json").exists()


def test_table2_prints_all_rows(capsys):
    assert main(["cost", "--table2"]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith(("instant-ngp", "b"))]
    assert len(lines) == 17
    assert "worst |error|" in out


def test_search_with_runs_draws_plot(tmp_path, capsys):
    runs = [
        _metrics(tmp_path / "r1", "b8k-t13", 26.9),
        _metrics(tmp_path / "r2", "b16k-t14", 27.0),
        _metrics(tmp_path / "r3", "b32k-t14", 27.3),  # best PSNR but 44 MB: over the budget
        _metrics(tmp_path / "r4", "b4k-t11", 21.0),
    ]
    png = tmp_path / "pareto.png"
    argv = ["cost", "--search", "--budget-l3", "32MB", "--runs", *map(str, runs)]
    assert main([*argv, "--plot", str(png), "--top", "3"]) == 0
    out = capsys.readouterr().out
    # r2 is best among fitting runs; r1 is within 0.25 dB and smaller -> chosen
    assert "chosen: r1" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_search_reads_the_trainers_metrics(tmp_path, capsys):
    """`dronecap train` writes the scores under "test" and the resolved config beside them."""
    run = tmp_path / "trained"
    run.mkdir()
    cfg = dataclasses.asdict(preset("tiny-dronerf-sized").replace(n_max=223))
    doc = {"test": {"psnr": 28.1, "ssim": 0.93, "views": 200}, "config": cfg}
    (run / "metrics.json").write_text(json.dumps(doc))
    argv = ["cost", "--search", "--budget-l3", "32MB", "--runs", str(run / "metrics.json")]
    assert main([*argv, "--plot", str(tmp_path / "p.png")]) == 0
    assert "chosen: trained" in capsys.readouterr().out


@pytest.mark.parametrize("doc", ["not json", '{"psnr": NaN, "config": {}}', '{"config": {}}'])
def test_search_refuses_bad_metrics(tmp_path, capsys, doc):
    bad = tmp_path / "metrics.json"
    bad.write_text(doc)
    argv = ["cost", "--search", "--budget-l3", "32MB", "--runs", str(bad)]
    assert main([*argv, "--plot", str(tmp_path / "p.png")]) == 1
    assert "metrics.json" in capsys.readouterr().err
    assert not (tmp_path / "p.png").exists()


def test_search_without_runs_uses_paper_points(tmp_path, capsys):
    png = tmp_path / "p.png"
    assert main(["cost", "--search", "--budget-l3", "32MB", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "paper's Table II" in out and "chosen: b8k-t13" in out  # the paper's own choice
    assert png.exists()


def test_search_nothing_fits(tmp_path, capsys):
    png = tmp_path / "p.png"
    assert main(["cost", "--search", "--budget-l3", "1MB", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("0 configurations fit") and "no Table II row fits" in out


def test_search_budgets_filter():
    grid = {"batch_samples": (4096, 65536), "log2_hashmap": (11, 16)}
    fits = search(Budget(l3=32_000_000), grid=grid)
    # 64k samples x 762 B = 50 MB of activations: never fits; 2^16 rows x 16 levels x 32 B
    # = 33.5 MB of state: never fits; only (4096, 2^11) remains
    assert [(r["batch_samples"], r["log2_hashmap"]) for r in fits] == [(4096, 11)]
    assert search(Budget(l2=100_000), grid=grid) == []  # a 1024-sample tile needs > 1 MB of L2


def test_pareto_and_choice():
    cfg = preset("tiny-dronerf")
    pts = [
        Point("a", cfg, 25.0, mem_mb=10),
        Point("b", cfg, 27.0, mem_mb=20),
        Point("c", cfg, 26.0, mem_mb=30),  # dominated by b
        Point("d", cfg, 27.2, mem_mb=40, fits=False),
    ]
    assert [p.label for p in pareto_front(pts)] == ["a", "b", "d"]
    assert choose(pts, 0.25).label == "b"
    assert choose(pts, 2.5).label == "a"
    assert choose([pts[3]]) is None


def test_parse_set_and_config_from_dict():
    cfg = apply_sets(preset("tiny-dronerf"), ["batch_samples=4096", "lr=0.5", "auto_n_max=true"])
    assert (cfg.batch_samples, cfg.lr, cfg.auto_n_max) == (4096, 0.5, True)
    assert apply_sets(cfg, ["betas=0.8,0.9"]).betas == (0.8, 0.9)
    with pytest.raises(ValueError):
        apply_sets(cfg, ["auto_n_max=maybe"])
    back = config_from_dict({**dataclasses.asdict(cfg), "unknown": 1})
    assert back == cfg


def test_steps_to_a_psnr_reads_the_curve():
    cfg = preset("tiny-dronerf").replace(steps=1000)
    pt = Point("r", cfg, 28.0, curve=[(100, 20.0), (300, 26.0), (500, 27.1), (700, 26.9)])
    assert pt.steps_to(27.0) == 500  # the first check at or above the target
    assert pt.steps_to(27.5) == 1000  # only the final test score reaches it
    assert pt.steps_to(29.0) is None


def test_search_ranks_runs_by_energy_to_a_psnr(tmp_path, capsys):
    cfg = dataclasses.asdict(preset("tiny-dronerf").replace(steps=2000))
    curves = {"slow": [(1500, 27.0)], "fast": [(400, 26.0), (800, 27.2)], "never": [(2000, 25)]}
    runs = []
    for name, curve in curves.items():
        (tmp_path / name).mkdir()
        doc = {"test": {"psnr": curve[-1][1]}, "config": cfg,
               "curve": [{"step": s, "seconds": s / 100, "psnr": p} for s, p in curve]}  # fmt: skip
        (tmp_path / name / "metrics.json").write_text(json.dumps(doc))
        runs.append(str(tmp_path / name / "metrics.json"))
    argv = ["cost", "--search", "--budget-l3", "32MB", "--runs", *runs, "--target-psnr", "27"]
    assert main([*argv, "--plot", str(tmp_path / "p.png")]) == 0
    out = capsys.readouterr().out
    table = out[out.index("cheapest energy first") :].splitlines()
    order = [ln.split()[0] for ln in table[2:5]]
    assert order == ["fast", "slow", "never"]
    fast, slow = (next(ln.split() for ln in table if ln.startswith(n)) for n in ("fast", "slow"))
    assert (fast[1], slow[1]) == ("800", "1500")
    # same model: energy grows with the steps (the warm-up is paid by both)
    assert float(fast[3]) < float(slow[3])
    assert "never reached" in out and "SoC power: 60 mW" in out and "ASSUMPTION" in out


@pytest.mark.parametrize("counts", ["trained", "marched"])
def test_run_dir_cost_uses_the_runs_samples(tmp_path, counts):
    """A run's compaction share changes its step cost: with B counting the marched samples a
    step trains on fewer (cheaper); with B counting the trained ones it marches more (the
    pre-pass on B / 0.43 samples, dearer)."""
    cfg = preset("scene-sized").replace(
        n_max=223, log2_hashmap=14, grid_res=64, batch_counts=counts
    )
    _run_json(tmp_path / "run", cfg)
    assert main(["cost", str(tmp_path / "run")]) == 0  # still training: no metrics.json yet
    before = json.loads((tmp_path / "run" / "cost.json").read_text())
    samples = {"marched": 1000, "trained": 430, "hull_fraction": 0.389}
    (tmp_path / "run" / "metrics.json").write_text(json.dumps({"samples": samples}))
    assert main(["cost", str(tmp_path / "run")]) == 0
    after = json.loads((tmp_path / "run" / "cost.json").read_text())
    assert before["assumptions"]["trained_fraction"] == 1.0
    assert after["assumptions"]["trained_fraction"] == pytest.approx(0.43)
    assert after["assumptions"]["hull_fraction"] == pytest.approx(0.389)
    cheaper = after["latency"]["train"] < before["latency"]["train"]
    assert cheaper == (counts == "marched")


def test_grid_rule_option_costs_the_papers_fixed_schedule(tmp_path):
    """The paper's run (every 256 steps, no warm-up) as flown: 39 updates in 10k steps; the
    trainer's rule on the same settings updates every step at first (340 updates)."""
    sets = ["--preset", "tiny-dronerf", "--set", "grid_every=256", "--set", "grid_warmup=0"]
    reps = {}
    for rule in ("fixed", "trainer"):
        out = tmp_path / f"{rule}.json"
        assert main(["cost", *sets, "--grid-rule", rule, "--json", str(out)]) == 0
        reps[rule] = json.loads(out.read_text())
    assert reps["fixed"]["assumptions"]["grid_updates"] == {"warmup": 0, "steady": 39}
    assert reps["trainer"]["assumptions"]["grid_updates"] == {"warmup": 0, "steady": 340}
    assert reps["fixed"]["latency"]["train"] < reps["trainer"]["latency"]["train"]
