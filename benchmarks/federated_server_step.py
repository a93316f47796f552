"""FedAvg's server step on lego IID: plain averaging vs FedAvgM (server learning rate, momentum).

Reports federations that ``benchmarks/federated_lego.py`` ran, one work folder per variant, all
on the same schedule, shards and baselines (copy the baselines and the pretraining of one
folder into the others to save time: they do not depend on the server step). Made with, per
variant (6k-step schedule, IID):

    .venv/bin/python benchmarks/federated_lego.py --work /tmp/fedm_lr2m5 --pretrain 2000 \\
        --local-steps 500 --rounds 8 --schemes iid --compress --server-lr 2 \\
        --server-momentum 0.5 --results exp_lr2m5 [--only federated | --only score]

then:

    .venv/bin/python benchmarks/federated_server_step.py /tmp/fedbench3 /tmp/fedm_lr2 ...

Prints one row per folder (server step, global PSNR per round on the curves' test views, final
PSNR on all test views against the best single drone and centralized) and writes
benchmarks/results/federated_server_step.md and .png (PSNR per round, one line per variant).
A federation stopped early is reported at its last round.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dronecap.federated import state as fed
from dronecap.federated.plot import save_png
from dronecap.files import atomic_output

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def load_variant(work: Path, scheme: str) -> dict:
    """Settings, per-round PSNR and final scores of ``work/<scheme>_fp16``."""
    run = work / f"{scheme}_fp16"
    s = fed.load_settings(run)
    scores_file = run / "final_scores_all.json"
    scores = json.loads(scores_file.read_text()) if scores_file.exists() else {}
    singles = {k: v["psnr"] for k, v in scores.items() if k.startswith("client_")}
    best = max(singles, key=singles.get, default=None)
    step = f"FedAvgM lr {s.server_lr:g}, momentum {s.server_momentum:g}"
    return {
        "work": str(work),
        "step": "FedAvg" if (s.server_lr, s.server_momentum) == (1.0, 0.0) else step,
        "schedule": f"N_pt {s.pretrain}, N_l {s.local_steps}, R {s.rounds}",
        "curve": [(r["round"], r["psnr"]) for r in fed.load_rounds(run)],
        "rounds_planned": s.rounds,
        "federated": scores.get("federated", {}).get("psnr"),
        "best_name": best,
        "best_single": singles.get(best),
        "centralized": scores.get("centralized", {}).get("psnr"),
    }


def held_out_psnr(run: Path, names: list[str]) -> dict[str, float]:
    """Mean PSNR of the named models of ``run`` (``federated``: ``checkpoint.pt``; others:
    ``baselines/<name>.pt``) on the test views the per-round curves did NOT use, i.e. views no
    server step was chosen on; cached in ``RUN/held_out_scores.json``."""
    import numpy as np
    import torch

    from dronecap.nerf.trainer import Trainer

    cache = run / "held_out_scores.json"
    scores = json.loads(cache.read_text()) if cache.exists() else {}
    s = fed.load_settings(run)
    test = fed.test_split(s.shards[0])
    curve = set(np.linspace(0, test.n - 1, s.eval_views).round().astype(int).tolist())
    held_out = [i for i in range(test.n) if i not in curve]
    torch.set_num_threads(1)
    for name in names:
        ckpt = run / fed.FINAL if name == "federated" else run / "baselines" / f"{name}.pt"
        if name in scores or not ckpt.exists():
            continue
        scores[name] = Trainer.load(ckpt).evaluate(test, views=held_out, progress=True)["psnr"]
        with atomic_output(cache) as tmp:
            tmp.write_text(json.dumps(scores, indent=1))
    return scores


def report(rows: list[dict], scheme: str) -> str:
    """Markdown table of the variants."""

    def db(x: float | None) -> str:
        return "-" if x is None else f"{x:.2f}"

    lines = [
        f"# Server step of the federation: lego {scheme.upper()}, 4 drones x 25 images",
        "",
        "Curve: global-model PSNR after each round on the run's curve views (20 evenly spaced",
        "test views); final: all 200 test views; best single drone and centralized: the same",
        "step budget (benchmarks/federated_lego.py). Made by benchmarks/federated_server_step.py.",
        "Held-out views: the 180 test views outside the curves' 20, on which no variant was",
        "chosen (with --held-out; the baselines scored in the first folder, which all share).",
        "",
        "| server step | schedule | PSNR per round (curve views) | final | best single | "
        "centralized | final - best single | held-out views: final - best single |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        curve = " ".join(f"{p:.2f}" for _, p in r["curve"])
        last = r["curve"][-1][0]
        if last < r["rounds_planned"]:
            curve += f" (stopped after round {last})"
        gain = (
            f"{r['federated'] - r['best_single']:+.2f}"
            if r["federated"] is not None and r["best_single"] is not None
            else "-"
        )
        lines.append(
            f"| {r['step']} | {r['schedule']} | {curve} | {db(r['federated'])} | "
            f"{db(r['best_single'])} | {db(r['centralized'])} | {gain} | "
            f"{r.get('held_out_gain', '-')} |"
        )
    lines += ["", "![PSNR per round](federated_server_step.png)", ""]
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """PSNR per round, one line per variant; the best single drone as a dotted line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for r in rows:
        x, y = zip(*r["curve"], strict=True)
        ax.plot(x, y, "o-", label=r["step"])
    singles = [r["best_single"] for r in rows if r["best_single"] is not None]
    if singles:
        ax.axhline(max(singles), color="gray", ls=":", label="best single drone (all views)")
    ax.set_xlabel("round")
    ax.set_ylabel("global-model PSNR [dB]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_png(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("works", nargs="+", type=Path, help="federated_lego.py work folders")
    ap.add_argument("--scheme", default="iid", choices=("iid", "sector"))
    ap.add_argument(
        "--held-out",
        action="store_true",
        help="also score the final models on the test views the curves did not use",
    )
    a = ap.parse_args()
    rows = [load_variant(w, a.scheme) for w in a.works]
    if a.held_out:
        best = rows[0]["best_name"]
        single = held_out_psnr(a.works[0] / f"{a.scheme}_fp16", [best])[best]
        for row, work in zip(rows, a.works, strict=True):
            mine = held_out_psnr(work / f"{a.scheme}_fp16", ["federated"]).get("federated")
            if mine is not None:
                row["held_out_gain"] = f"{mine - single:+.2f} ({mine:.2f} vs {single:.2f})"
    text = report(rows, a.scheme)
    with atomic_output(RESULTS / "federated_server_step.md") as tmp:
        tmp.write_text(text)
    plot(rows, RESULTS / "federated_server_step.png")
    print(text)


if __name__ == "__main__":
    main()
