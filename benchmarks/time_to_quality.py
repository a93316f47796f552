"""Time to quality: test PSNR against training wall time, over presets and time budgets.

Each `run` trains one configuration on one scene (lego RGB or gray at 160 px, or any dataset
file) and writes ``benchmarks/results/time_to_quality/NAME.json``: a curve of PSNR on every
10th test view against training seconds (evaluation time excluded), the final mean PSNR/SSIM
over ALL test views, ms/step and the render time per view. Training time is the process
CPU time of the optimizer steps (what a 1-thread run takes on an idle core: the machine is
shared, so wall time is not); ``--time-budget`` plans the schedule (nerf/budget.py) on that
clock, ``--target-psnr`` and ``--plateau-db`` stop on validation views. `report` gathers them into
``benchmarks/results/time_to_quality.md`` and ``time_to_quality.png`` with the paper's GPU
point (26.94 dB in 28 s) drawn for reference.

    .venv/bin/python benchmarks/time_to_quality.py run sized --preset scene-sized
    .venv/bin/python benchmarks/time_to_quality.py run paper --preset tiny-dronerf
    .venv/bin/python benchmarks/time_to_quality.py run budget60 --time-budget 60
    .venv/bin/python benchmarks/time_to_quality.py report
    .venv/bin/python benchmarks/time_to_quality.py compare --budget 10 --rounds 3

`compare` trains the old default (``OLD_DEFAULT``: today's with the changes undone) and the new
one on lego, the simulated corridor and the real Himax test_23 sequence (built as
benchmarks/scene_sized.py builds them), taking turns in one process, and writes
``benchmarks/results/time_to_quality_compare.md`` and ``.png`` (``--out``). ``--old`` and
``--new`` give each side its own ``FIELD=VALUE`` overrides of today's default (a candidate
default is ``--old`` with nothing against ``--new lr=0.015``).

Single thread (``--threads 1``) unless told; run under ``nice`` on the shared machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import _runs as shared
import numpy as np

RUNS = shared.RESULTS / "time_to_quality"
PAPER_GPU = (28.0, 26.94)  # the paper's lego result on a GPU: seconds, dB


def run(args: argparse.Namespace) -> None:
    """Train one configuration and write its JSON (partial while training)."""
    import torch

    from dronecap.gap9.model import memory_bytes
    from dronecap.nerf import budget
    from dronecap.nerf.budget import BudgetConfig
    from dronecap.nerf.config import parse_field, preset
    from dronecap.nerf.resolve import resolve
    from dronecap.nerf.trainer import Trainer

    torch.set_num_threads(args.threads)
    changes = {}
    for item in args.set:
        k, v = item.split("=", 1)
        changes[k] = parse_field(k, v)
    cfg = preset(args.preset).replace(seed=args.seed, **changes)
    if args.steps:
        cfg = cfg.replace(steps=args.steps)
    ds = shared.open_scene(args.scene, Path(args.cache))
    test = np.flatnonzero(ds.split == 2)
    pool = np.flatnonzero(ds.split == 1)  # validation views decide stops, test views score
    pool = pool if pool.size else test
    held_out = np.unique(pool[np.linspace(0, pool.size - 1, 5).astype(int)])
    curve_views = test[:: args.curve_every_view]
    bcfg = BudgetConfig(args.time_budget, args.target_psnr, args.plateau_db)
    state = budget.start(bcfg, cfg.steps)
    tr = Trainer(resolve(cfg, ds, memory_fn=memory_bytes), ds)  # sized as `dronecap train` does
    curve, ms = [], []
    cpu = 0.0  # process CPU seconds of the optimizer steps: idle-core time of a 1-thread run
    next_eval = args.eval_every
    t_start = time.time()
    tr.field.train()
    while not budget.finished(state, tr.step):
        tr.plan(state.planned_steps)  # the lr decay follows the plan
        c0 = time.process_time()
        ms.append(tr.train_step()["ms"])
        dt = time.process_time() - c0
        cpu += dt
        budget.after_step(bcfg, state, tr.step, cpu, dt)
        if budget.check_due(bcfg, state, tr.step) and (args.target_psnr or args.plateau_db):
            why = budget.record_check(bcfg, state, tr.step, cpu, tr.evaluate(ds, held_out)["psnr"])
            tr.field.train()
            if why:
                print(f"{args.name}: stop at step {tr.step}: {why}")
        if cpu >= next_eval and not budget.finished(state, tr.step):
            next_eval += args.eval_every
            ev = tr.evaluate(ds, curve_views)
            tr.field.train()
            curve.append({"step": tr.step, "seconds": cpu, "psnr": ev["psnr"]})
            shared.write_run(RUNS, {"name": args.name, "finished": False, "curve": curve})
            print(f"{args.name}: step {tr.step} {cpu:.0f} CPU s psnr {ev['psnr']:.2f}", flush=True)
    out, curve_psnr = shared.final_record(args, tr, ds, curve_views, ms, t_start)
    curve.append({"step": tr.step, "seconds": cpu, "psnr": curve_psnr})
    out |= {
        "scene": args.label or args.scene,
        "curve": curve,
        "cpu_seconds": cpu,
        "budget": dataclasses.asdict(bcfg),
        "stop_reason": state.stop_reason,
        "reasons": dict(tr.resolved.reasons),
    }
    shared.write_run(RUNS, out | {"finished": True})
    print(
        f"{args.name}: PSNR {out['psnr']:.2f} SSIM {out['ssim']:.3f} over {out['views']} "
        f"views, {cpu:.0f} CPU s, {np.median(ms):.1f} ms/step (wall), "
        f"render {out['render_seconds']:.3f} s/view"
    )


def report(args: argparse.Namespace) -> None:
    """Table and plot of every finished run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = shared.read_runs(RUNS)
    stopped = [r for r in runs if not r.get("finished") and r["curve"]]
    runs = [r for r in runs if r.get("finished")]
    load = os.getloadavg()
    lines = [
        "# Time to quality (PSNR against training wall time)",
        "",
        "Final PSNR/SSIM: scikit-image over ALL test views at the stored resolution; the curve "
        "(plot) uses every 10th test view, evaluation time excluded. Training time is process "
        "CPU time of the optimizer steps (1 torch thread unless the `thr` column says "
        "otherwise: the time the run takes on an idle core), measured under `nice` on the "
        "shared 2-core machine; ms/step and render s/view are wall times under that load (the "
        "`load` column, "
        "1-minute load average at the end of each run): not comparable between rows. The paper's "
        "GPU point: "
        f"{PAPER_GPU[1]} dB in {PAPER_GPU[0]:.0f} s.",
        "",
        "Command: the `run` lines in docs/training.md; this table: "
        f"`.venv/bin/python benchmarks/time_to_quality.py report` (load {load[0]:.1f}).",
        "",
        "| run | scene | preset + overrides | until | steps | PSNR dB | SSIM | train CPU s | "
        "ms/step | render s/view | GAP9 MB | n_max / march / grid (update every) / log2 T | thr | "
        "load |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|",
    ]
    for r in runs:
        b, c = r["budget"], r["config"]
        until = f"{b['time_budget_s']:g} s" if b["time_budget_s"] else "steps"
        until += f", {r['stop_reason']}" if r["stop_reason"] else ""
        grid = f"{c['grid_res']} (every {c['grid_every']})"
        sizes = f"{c['n_max']} / {c['march_steps']} / {grid} / {c['log2_hashmap']}"
        lines.append(
            f"| {r['name']} | {r['scene']} | {r['preset']} "
            f"{' '.join(r['overrides'])} | {until} | {r['steps']} | {r['psnr']:.2f} | "
            f"{r['ssim']:.3f} | {r['cpu_seconds']:.0f} | {r['ms_per_step_median']:.1f} | "
            f"{r['render_seconds']:.2f} | {shared.memory_mb(c):.1f} | {sizes} | {r['threads']} | "
            f"{r['load_average']:.1f} |"
        )
    lines += shared.stopped_table(
        stopped,
        "Runs that died before their final evaluation (lego; PSNR on every 10th test view, "
        "20 views, at the last check):",
        "train CPU s",
    )
    shared.write_page(lines, shared.RESULTS / "time_to_quality.md")
    scenes = sorted({r["scene"] for r in runs})
    fig, axes = plt.subplots(1, len(scenes), figsize=(6 * len(scenes), 4.2), squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        for r in (r for r in runs + stopped if r.get("scene", "lego") == scene):
            c = r["curve"]
            ax.plot([p["seconds"] for p in c], [p["psnr"] for p in c], "o-", ms=3, label=r["name"])
        if scene == "lego":
            ax.plot(*PAPER_GPU, "k*", ms=12, label="paper, GPU")
        ax.set_xlabel("training time [CPU s, 1 thread]")
        ax.set_ylabel("test PSNR [dB] (every 10th test view)")
        ax.set_title(scene)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(shared.RESULTS / "time_to_quality.png", dpi=110)


# The default before this session's changes, as overrides of today's: what `compare` runs as
# "old" beside the current default ("new") in the same process.
OLD_DEFAULT = ("mlp_dtype=auto", "grid_ramp=16")  # session 22's changes undone
COMPARE_SCENES = ("lego", "corridor", "himax-test_23")


def _budget_run(ds, cfg, budget_s: float, views: np.ndarray) -> dict:
    """Train ``cfg`` for ``budget_s`` process-CPU seconds of optimizer steps (the schedule
    planned as ``--time-budget`` plans it) and score ``views`` at a quarter, half and all of
    the budget. Returns {"setup_s": CPU s to build the trainer (grid carving included),
    "steps", "curve": [(CPU s, PSNR dB)], "psnr": the last}."""
    from dronecap.gap9.model import memory_bytes
    from dronecap.nerf import budget
    from dronecap.nerf.budget import BUDGET_LR_FINAL_RATIO, BudgetConfig
    from dronecap.nerf.resolve import resolve
    from dronecap.nerf.trainer import Trainer

    c0 = time.process_time()
    tr = Trainer(resolve(cfg.replace(lr_final_ratio=BUDGET_LR_FINAL_RATIO), ds, memory_bytes), ds)
    setup = time.process_time() - c0
    bcfg = BudgetConfig(time_budget_s=budget_s)
    state = budget.start(bcfg, cfg.steps)
    cpu, marks, curve = 0.0, [budget_s / 4, budget_s / 2], []
    while not budget.finished(state, tr.step):
        tr.plan(state.planned_steps)
        c0 = time.process_time()
        tr.train_step()
        dt = time.process_time() - c0
        cpu += dt
        budget.after_step(bcfg, state, tr.step, cpu, dt)
        if marks and cpu >= marks[0] and not budget.finished(state, tr.step):
            marks.pop(0)
            curve.append((cpu, tr.evaluate(ds, views)["psnr"]))
            tr.field.train()
    curve.append((cpu, tr.evaluate(ds, views)["psnr"]))
    return {"setup_s": setup, "steps": tr.step, "curve": curve, "psnr": curve[-1][1]}


def compare(args: argparse.Namespace) -> None:
    """Old default against the new one on each scene, in the same process, taking turns for
    ``--rounds`` rounds; table (medians over rounds) and plot."""
    import torch
    from scene_sized import build_scene

    from dronecap.nerf.config import apply_sets, preset

    torch.set_num_threads(args.threads)
    variants = {"old": args.old, "new": args.new}
    rows: dict[tuple[str, str], list[dict]] = {}
    for rnd in range(args.rounds):
        for scene in args.scenes.split(","):
            ds = shared.open_scene(str(build_scene(scene, Path(args.cache))), Path(args.cache))
            test = np.flatnonzero(ds.split == 2)
            views = test[:: max(1, test.size // 20)]  # at most ~20 views scored
            for name, sets in variants.items():
                cfg = apply_sets(preset("scene-sized").replace(seed=args.seed + rnd), sets)
                out = _budget_run(ds, cfg, args.budget, views) | {"load": os.getloadavg()[0]}
                rows.setdefault((scene, name), []).append(out)
                done = f"{out['psnr']:.2f} dB, {out['steps']} steps, setup {out['setup_s']:.1f}"
                print(
                    f"round {rnd} {scene} {name}: {done} CPU s, load {out['load']:.1f}", flush=True
                )
    _compare_report(args, variants, rows)


def _compare_report(args: argparse.Namespace, variants: dict, rows: dict) -> None:
    """benchmarks/results/time_to_quality_compare.md and .png from ``compare``'s rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = args.scenes.split(",")
    lines = [
        f"# Time to quality: old default against new, {args.budget:g} CPU s on 1 thread",
        "",
        f"`.venv/bin/python benchmarks/time_to_quality.py compare --budget {args.budget:g} "
        f"--rounds {args.rounds} --scenes {args.scenes}`; old = today's default + "
        f"`{' '.join(args.old)}`, new = today's default + `{' '.join(args.new)}`. "
        "Training clock: process CPU time of the optimizer steps "
        "(the time on an idle core; the machine is shared), the schedule planned as "
        "`--time-budget` plans it. PSNR on up to 20 test views spread over the test split. "
        "Medians over rounds (seed + round); `setup` is the CPU time to build the trainer "
        "(grid carving included), outside the budget; `load`: 1-minute load average after "
        "each run (median).",
        "",
        "| scene | variant | PSNR dB (median) | rounds | steps | setup CPU s | load |",
        "|---|---|---:|---|---:|---:|---:|",
    ]
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 3.8), squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        for name in variants:
            runs = rows[(scene, name)]
            med = lambda k, rs=runs: float(np.median([r[k] for r in rs]))  # noqa: E731
            each = " / ".join(f"{r['psnr']:.2f}" for r in runs)
            lines.append(f"| {scene} | {name} | {med('psnr'):.2f} | {each} | {med('steps'):.0f} | "
                         f"{med('setup_s'):.1f} | {med('load'):.1f} |")  # fmt: skip
            style = {"fmt": "o-", "color": "C1"} if name == "new" else {"fmt": "s--", "color": "C0"}
            for i, r in enumerate(runs):
                secs, psnrs = zip(*r["curve"], strict=True)
                ax.plot(secs, psnrs, style["fmt"], ms=3, color=style["color"],
                        label=name if i == 0 else None)  # fmt: skip
        ax.set_title(scene)
        ax.set_xlabel("training time [CPU s, 1 thread]")
        ax.set_ylabel("test PSNR [dB]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    shared.write_page(lines, shared.RESULTS / f"{args.out}.md")
    fig.tight_layout()
    fig.savefig(shared.RESULTS / f"{args.out}.png", dpi=110)


def main() -> None:
    """Command line."""
    p, r = shared.command_line(__doc__)
    r.add_argument("--scene", default="lego", help="lego, lego-gray or a dataset.h5 path")
    r.add_argument("--label", help="scene name in the table and plot (default: --scene)")
    r.add_argument("--preset", default="tiny-dronerf-sized")
    r.add_argument("--steps", type=int, default=0, help="override the preset's step count")
    r.add_argument("--eval-every", type=float, default=15.0, help="training CPU seconds")
    r.add_argument("--time-budget", type=float, help="CPU seconds of training (planned)")
    r.add_argument("--target-psnr", type=float, help="stop at this held-out PSNR")
    r.add_argument("--plateau-db", type=float, default=0.0, help="plateau stop (0: none)")
    c = p._subparsers._group_actions[0].add_parser("compare", help="old default vs new")
    c.add_argument("--scenes", default=",".join(COMPARE_SCENES))
    c.add_argument("--budget", type=float, default=10.0, help="CPU seconds of training")
    c.add_argument("--rounds", type=int, default=3)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--threads", type=int, default=1)
    c.add_argument("--cache", default="/tmp/dronecap-time-to-quality")
    c.add_argument("--old", nargs="*", default=list(OLD_DEFAULT), help="FIELD=VALUE of 'old'")
    c.add_argument("--new", nargs="*", default=[], help="FIELD=VALUE of 'new' (default: none)")
    c.add_argument("--out", default="time_to_quality_compare", help="results file name")
    args = p.parse_args()
    {"run": run, "report": report, "compare": compare}[args.cmd](args)


if __name__ == "__main__":
    main()
