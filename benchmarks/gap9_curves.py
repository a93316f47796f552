"""Modelled GAP9 time and energy to a target PSNR, from the first steps of real training runs.

Each variant (today's default with ``FIELD=VALUE`` overrides) trains lego 160 px RGB on one
thread with the default 10k-step schedule (its learning-rate decay spans 10k steps), scored on
--views test views every --every steps until the score passes --target (plus --margin) or
--max-steps; each run's ``metrics.json`` (curve, resolved configuration, trained samples) is
costed by ``dronecap cost --search``'s model (:func:`dronecap.gap9.search.to_target`): GAP9
minutes and joules to the first check at or above the target. Several seeds per variant, in
turn; the table gives each run and the median per variant. A run --work already holds
(``NAME_sSEED/metrics.json``) is reused unless --fresh. Usage::

    PYTHONPATH=. .venv/bin/python benchmarks/gap9_curves.py --work /tmp/g9 \
        --variants default "lr15:lr=0.015" --seeds 0 1 2 --out gap9_curves

Writes benchmarks/results/<out>.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
from snapshot import DATA, RESULTS

LEGO = DATA / "nerf_synthetic_160" / "lego"


def variant(spec: str) -> tuple[str, list[str]]:
    """ "name:field=v,field=v" (or "default") -> (name, ["field=v", ...])."""
    name, _, sets = spec.partition(":")
    return name, [s for s in sets.split(",") if s]


def curve_run(ds, sets: list[str], seed: int, args: argparse.Namespace, out: Path) -> dict:
    """Train until the target is passed; write and return the run's metrics.json record."""
    from dronecap.gap9.model import memory_bytes
    from dronecap.nerf.config import apply_sets, preset
    from dronecap.nerf.resolve import resolve
    from dronecap.nerf.trainer import Trainer

    test = np.flatnonzero(ds.split == 2)
    views = test[:: max(1, test.size // args.views)]
    cfg = apply_sets(preset("scene-sized").replace(seed=seed), sets)
    tr = Trainer(resolve(cfg, ds, memory_bytes), ds)
    curve, cpu = [], 0.0
    while tr.step < args.max_steps:
        c0 = time.process_time()
        tr.train(args.every)
        cpu += time.process_time() - c0
        curve.append({"step": tr.step, "psnr": tr.evaluate(ds, views)["psnr"]})
        tr.field.train()
        if curve[-1]["psnr"] >= args.target + args.margin:
            break
    doc = {
        "psnr": curve[-1]["psnr"],
        "config": dataclasses.asdict(tr.cfg),
        "curve": curve,
        "samples": tr.sample_counts(),
        "train_cpu_s": round(cpu, 1),
        "load": os.getloadavg()[0],
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(doc, default=list))
    return doc


def main() -> None:
    import torch

    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset
    from dronecap.gap9.search import load_runs, to_target

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/dronecap-gap9-curves"))
    ap.add_argument("--variants", nargs="+", default=["default"], help='"name:f=v,f=v"')
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--every", type=int, default=100, help="steps between checks")
    ap.add_argument("--views", type=int, default=20, help="test views per check")
    ap.add_argument("--max-steps", type=int, default=3000)
    ap.add_argument("--target", type=float, default=26.94, help="PSNR dB (the paper's)")
    ap.add_argument("--margin", type=float, default=0.15, help="dB past the target to stop")
    ap.add_argument("--out", default="gap9_curves")
    ap.add_argument("--fresh", action="store_true", help="redo runs --work already holds")
    args = ap.parse_args()
    torch.set_num_threads(1)
    lego = args.work / "lego.h5"
    if not lego.exists():
        args.work.mkdir(parents=True, exist_ok=True)
        import_blender(LEGO, lego, progress=False)
    ds = open_dataset(lego)
    lines = [
        f"# Modelled GAP9 cost to {args.target:g} dB from the first steps of lego runs",
        "",
        f"Command: `benchmarks/gap9_curves.py --variants {' '.join(args.variants)} --seeds "
        f"{' '.join(map(str, args.seeds))} --every {args.every} --views {args.views}`. One "
        "thread, the default 10k-step schedule; steps = first check at or above the target; "
        "GAP9 minutes and joules from `dronecap cost --search`'s model with the run's trained "
        "share and hull; `load` = 1-minute load average after the run.",
        "",
        "| variant | seed | steps to target | GAP9 min | energy J | last PSNR dB | load |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    medians = []
    for spec in args.variants:
        name, sets = variant(spec)
        mins = []
        for seed in args.seeds:
            out = args.work / f"{name}_s{seed}"
            if (out / "metrics.json").exists() and not args.fresh:  # a run of an earlier call
                doc = json.loads((out / "metrics.json").read_text())
            else:
                doc = curve_run(ds, sets, seed, args, out)
            row = to_target(load_runs([out / "metrics.json"]), args.target)[0]
            mins.append(row["minutes"] if row["minutes"] is not None else float("inf"))
            cost = (
                f"{row['steps']} | {row['minutes']:.1f} | {row['joules']:.1f}"
                if row["steps"] is not None
                else "not reached | | "
            )
            load = f"{doc['load']:.1f}" if "load" in doc else ""
            lines.append(f"| {name} | {seed} | {cost} | {doc['psnr']:.2f} | {load} |")
            print(lines[-1], flush=True)
        medians.append(
            f"| {name} (`{' '.join(sets) or 'today'}`) | {statistics.median(mins):.1f} |"
        )
    lines += ["", "| variant | median GAP9 min to target |", "|---|---:|", *medians]
    (RESULTS / f"{args.out}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-len(medians) - 3 :]))


if __name__ == "__main__":
    main()
