"""Trainer accuracy against time: lego 160 px, test PSNR/SSIM on all test views, curves.

Each `run` trains one configuration (a preset plus overrides, one seed) on the lego scene
(RGB or gray) and writes ``benchmarks/results/train_runs/NAME.json``: the final mean PSNR/SSIM
over ALL 200 test views (scikit-image, 160x160), a curve of PSNR on every 10th test view
against steps and wall-clock seconds, ms/step and the parameter count. `report` gathers the
JSON files into ``benchmarks/results/train_accuracy.md`` and ``train_accuracy.png``.

    .venv/bin/python benchmarks/train_accuracy.py run tiny-s0 --preset tiny-dronerf --seed 0
    .venv/bin/python benchmarks/train_accuracy.py run gray-s0 --preset tiny-dronerf --gray
    .venv/bin/python benchmarks/train_accuracy.py report
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
RUNS = RESULTS / "train_runs"
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"


def dataset(gray: bool, cache: Path):
    """The lego dataset (imported once into ``cache``)."""
    from dronecap.datasets.blender import import_blender
    from dronecap.datasets.format import open_dataset

    path = cache / ("lego_gray.h5" if gray else "lego.h5")
    if not path.exists():
        import_blender(LEGO, path, color="gray" if gray else "rgb", progress=False)
    return open_dataset(path)


def run(args: argparse.Namespace) -> None:
    """Train one configuration and write its JSON."""
    import torch

    from dronecap.nerf.config import apply_sets, preset
    from dronecap.nerf.trainer import Trainer

    torch.set_num_threads(args.threads)
    cfg = apply_sets(preset(args.preset), args.set).replace(seed=args.seed)
    ds = dataset(args.gray, Path(args.cache))
    test = np.flatnonzero(ds.split == 2)
    curve_views = test[:: args.curve_every_view]
    tr = Trainer(cfg, ds)
    curve, ms = [], []
    marks = sorted({*range(args.eval_every, cfg.steps, args.eval_every)})
    t_start = time.time()
    for mark in [*marks, cfg.steps]:
        logs = tr.train(mark - tr.step, progress=args.progress)
        ms += [log["ms"] for log in logs]
        if mark != cfg.steps:
            ev = tr.evaluate(ds, curve_views)
            curve.append({"step": tr.step, "seconds": tr.train_seconds, "psnr": ev["psnr"]})
            _write(args.name, {"name": args.name, "finished": False, "curve": curve})
            print(
                f"{args.name}: step {tr.step} {tr.train_seconds:.0f}s"
                f" psnr(subset) {ev['psnr']:.2f}",
                flush=True,
            )
    full = tr.evaluate(ds)
    sub = float(np.mean([v["psnr"] for v in full["per_view"] if v["index"] in set(curve_views)]))
    curve.append({"step": tr.step, "seconds": tr.train_seconds, "psnr": sub})
    t0 = time.perf_counter()
    for i in test[:5]:
        tr.render(ds.poses[i], ds.intrinsics)
    render_s = (time.perf_counter() - t0) / 5
    out = {
        "name": args.name,
        "preset": args.preset,
        "overrides": args.set,
        "gray": args.gray,
        "seed": args.seed,
        "steps": tr.step,
        "psnr": full["psnr"],
        "ssim": full["ssim"],
        "views": full["views"],
        "per_view_psnr": [v["psnr"] for v in full["per_view"]],
        "curve": curve,
        "train_seconds": tr.train_seconds,
        "wall_seconds": time.time() - t_start,
        "ms_per_step_median": float(np.median(ms)),
        "render_seconds": render_s,
        "parameters": tr.parameter_count(),
        "n_max": tr.cfg.n_max,
        "threads": args.threads,
        "load_average": os.getloadavg()[0],
        "config": dataclasses.asdict(tr.cfg),  # resolved: n_max as trained
    }
    _write(args.name, out | {"finished": True})
    print(
        f"{args.name}: PSNR {full['psnr']:.2f} SSIM {full['ssim']:.3f} over {full['views']} "
        f"views, {tr.train_seconds:.0f} s, {np.median(ms):.1f} ms/step",
        flush=True,
    )


def _write(name: str, obj: dict) -> None:
    """Write one run's JSON (partial while training, complete at the end)."""
    RUNS.mkdir(parents=True, exist_ok=True)
    (RUNS / f"{name}.json").write_text(json.dumps(obj, indent=1, default=list) + "\n")


def memory_mb(cfg_dict: dict) -> float:
    """Modelled GAP9 memory (MB, the paper's Table II accounting: parameters, gradients, Adam
    state, activations, occupancy grid, image) of a run's configuration (gap9/model.py)."""
    from dronecap.gap9.model import cost_report
    from dronecap.nerf.config import config_from_dict

    return cost_report(config_from_dict(cfg_dict))["memory"]["untiled"]["total"] / 1e6


def report(args: argparse.Namespace) -> None:
    """Table and plot of all runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [json.loads(p.read_text()) for p in sorted(RUNS.glob("*.json"))]
    unfinished = [r for r in runs if not r.get("finished", True)]
    runs = [r for r in runs if r.get("finished", True)]
    groups: dict[str, list[dict]] = {}
    for r in runs:
        key = r["name"].rsplit("-s", 1)[0]
        groups.setdefault(key, []).append(r)
    lines = [
        "# Trainer accuracy and speed against error (lego, 160x160)",
        "",
        "Test PSNR/SSIM: scikit-image on the stored 160x160 resolution, mean over ALL test views "
        "(200 for lego), ground truth composited on the dataset's white background. "
        "Mean over seeds (± std when several). Times are training only (no evaluation), "
        "1 torch thread, on the shared 2-core machine (load average at the end of each run "
        "in the last column): compare rows with care. Rows with a load above 4 (tiny, "
        "fp16-3k, fp32-3k: session 1) ran while the machine was saturated and their times are "
        "inflated several-fold; the clean step times are in train_speed.md.",
        "",
        "Commands: see the `run` lines in docs/training.md; this table: "
        "`.venv/bin/python benchmarks/train_accuracy.py report`.",
        "",
        "| run | preset + overrides | seeds | steps | PSNR dB | SSIM | train s | ms/step | "
        "render s/view | params | GAP9 MB | n_max | load |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, rs in groups.items():
        p = [r["psnr"] for r in rs]
        s = [r["ssim"] for r in rs]
        r0 = rs[0]
        spread = f" ± {np.std(p):.2f}" if len(p) > 1 else ""
        over = " ".join(r0["overrides"]) + (" (gray)" if r0["gray"] else "")
        lines.append(
            f"| {key} | {r0['preset']} {over} | {','.join(str(r['seed']) for r in rs)} | "
            f"{r0['steps']} | {np.mean(p):.2f}{spread} | {np.mean(s):.3f} | "
            f"{np.mean([r['train_seconds'] for r in rs]):.0f} | "
            f"{np.mean([r['ms_per_step_median'] for r in rs]):.1f} | "
            f"{np.mean([r['render_seconds'] for r in rs]):.2f} | {r0['parameters']} | "
            f"{memory_mb(r0['config']):.1f} | {r0['n_max']} | "
            f"{np.mean([r['load_average'] for r in rs]):.1f} |"
        )
    if unfinished:
        lines += [
            "",
            "Runs stopped before their last step (time budget); PSNR on every 10th test view "
            "(20 views) at the last evaluated step:",
            "",
            "| run | step | train s | PSNR dB (20 views) |",
            "|---|---:|---:|---:|",
        ]
        for r in unfinished:
            c = r["curve"][-1]
            lines.append(f"| {r['name']} | {c['step']} | {c['seconds']:.0f} | {c['psnr']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (RESULTS / "train_accuracy.md").write_text(text)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for r in unfinished:
        psnr = [c["psnr"] for c in r["curve"]]
        label = f"{r['name']} (stopped)"
        ax[0].plot([c["seconds"] for c in r["curve"]], psnr, "x--", label=label)
        ax[1].plot([c["step"] for c in r["curve"]], psnr, "x--", label=label)
    for key, rs in groups.items():
        r0 = rs[0]
        steps = [c["step"] for c in r0["curve"]]
        secs = np.mean([[c["seconds"] for c in r["curve"]] for r in rs], 0)
        psnr = np.mean([[c["psnr"] for c in r["curve"]] for r in rs], 0)
        ax[0].plot(secs, psnr, "o-", label=key)
        ax[1].plot(steps, psnr, "o-", label=key)
    ax[0].set_xlabel("training wall-clock [s] (1 thread, shared machine)")
    ax[1].set_xlabel("optimizer steps")
    for a in ax:
        a.set_ylabel("test PSNR [dB] (every 10th test view)")
        a.grid(alpha=0.3)
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(RESULTS / "train_accuracy.png", dpi=110)


def main() -> None:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("name")
    r.add_argument("--preset", default="tiny-dronerf")
    r.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--gray", action="store_true")
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--eval-every", type=int, default=2500)
    r.add_argument("--curve-every-view", type=int, default=10)
    r.add_argument("--cache", default="/tmp/dronecap_bench")
    r.add_argument("--progress", action="store_true")
    sub.add_parser("report")
    args = p.parse_args()
    run(args) if args.cmd == "run" else report(args)


if __name__ == "__main__":
    main()
