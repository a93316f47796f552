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
import time
from pathlib import Path

import _runs as shared
import numpy as np

RUNS = shared.RESULTS / "train_runs"


def run(args: argparse.Namespace) -> None:
    """Train one configuration and write its JSON."""
    import torch

    from dronecap.nerf.config import apply_sets, preset
    from dronecap.nerf.trainer import Trainer

    torch.set_num_threads(args.threads)
    cfg = apply_sets(preset(args.preset), args.set).replace(seed=args.seed)
    ds = shared.open_scene("lego-gray" if args.gray else "lego", Path(args.cache))
    test = np.flatnonzero(ds.split == 2)
    curve_views = test[:: args.curve_every_view]
    tr = Trainer(cfg, ds)
    curve, ms = [], []
    marks = sorted({*range(args.eval_every, cfg.steps, args.eval_every)})
    t_start = time.time()
    for mark in [*marks, cfg.steps]:
        logs = tr.train(mark - tr.step)
        ms += [log["ms"] for log in logs]
        if mark != cfg.steps:
            ev = tr.evaluate(ds, curve_views)
            curve.append({"step": tr.step, "seconds": tr.train_seconds, "psnr": ev["psnr"]})
            shared.write_run(RUNS, {"name": args.name, "finished": False, "curve": curve})
            print(
                f"{args.name}: step {tr.step} {tr.train_seconds:.0f}s"
                f" psnr(subset) {ev['psnr']:.2f}",
                flush=True,
            )
    out, curve_psnr = shared.final_record(args, tr, ds, curve_views, ms, t_start)
    curve.append({"step": tr.step, "seconds": tr.train_seconds, "psnr": curve_psnr})
    out |= {"gray": args.gray, "curve": curve}
    shared.write_run(RUNS, out | {"finished": True})
    print(
        f"{args.name}: PSNR {out['psnr']:.2f} SSIM {out['ssim']:.3f} over {out['views']} "
        f"views, {tr.train_seconds:.0f} s, {np.median(ms):.1f} ms/step",
        flush=True,
    )


def report(args: argparse.Namespace) -> None:
    """Table and plot of all runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = shared.read_runs(RUNS)
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
            f"{shared.memory_mb(r0['config']):.1f} | {r0['n_max']} | "
            f"{np.mean([r['load_average'] for r in rs]):.1f} |"
        )
    lines += shared.stopped_table(
        unfinished,
        "Runs stopped before their last step (time budget); PSNR on every 10th test view "
        "(20 views) at the last evaluated step:",
        "train s",
    )
    shared.write_page(lines, shared.RESULTS / "train_accuracy.md")
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
    fig.savefig(shared.RESULTS / "train_accuracy.png", dpi=110)


def main() -> None:
    """Command line."""
    p, r = shared.command_line(__doc__)
    r.add_argument("--preset", default="tiny-dronerf")
    r.add_argument("--gray", action="store_true")
    r.add_argument("--eval-every", type=int, default=2500)
    args = p.parse_args()
    run(args) if args.cmd == "run" else report(args)


if __name__ == "__main__":
    main()
