"""A swarm's federation: FedAvg on the drone shards of a simulated swarm, variants of the exchange.

The swarm (issue 26): ``dronecap simulate --drones 4 --sensor aideck --frames 300``, default
``ingest``, ``sfm``, ``split``, ``shard --scheme drone`` -- a shard per drone holding what that
drone saw (its own part of the corridor, its own camera), plus the common test views. Each
variant is a ``dronecap federate`` run folder on those shards, all on one schedule and started
from the same pretraining (round 0 copied from the first folder: it does not depend on the
exchange); the first folder also holds the baselines (``--baselines``: centralized and each drone
alone, same step budget). Made with, per variant::

    dronecap federate shards --pretrain 2000 --local-steps 500 --rounds R --out RUN [flags]

then::

    python benchmarks/federated_swarm.py RUN_WITH_BASELINES RUN2 RUN3 ...

Prints one row per folder (the exchange, global PSNR per round on all test views, the last
round against the best single drone and centralized) and writes
benchmarks/results/federated_swarm.md and .png (PSNR per round; baselines as lines).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from dronecap.federated import state as fed
from dronecap.federated.plot import save_png
from dronecap.files import atomic_output
from dronecap.plots import pyplot

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def exchange(s: fed.FedSettings) -> str:
    """The variant's exchange in words: uploads, row averaging and the server step."""
    up = (
        f"sparse {s.sparse_rows:g} rows {s.quant_bits}-bit"
        if s.quant_bits
        else f"whole {s.transfer_dtype}"
    )
    rows = "visibility-weighted" if s.visibility and s.quant_bits else "plain mean"
    step = (
        "FedAvg"
        if (s.server_lr, s.server_momentum) == (1.0, 0.0)
        else f"FedAvgM lr {s.server_lr:g} m {s.server_momentum:g}"
    )
    table = ", table: mean change" if s.table_step == "mean" else ""
    return f"{up}, {rows}, {step}{table}"


def load_run(run: Path) -> dict:
    """Settings, PSNR per round and upload bytes of one federate run folder."""
    s = fed.load_settings(run)
    rounds = fed.load_rounds(run)
    ups = [r["bytes_up_total"] / max(r["participants"], 1) for r in rounds if r["round"] > 0]
    return {
        "run": str(run),
        "exchange": exchange(s),
        "schedule": f"N_pt {s.pretrain}, N_l {s.local_steps}, R {s.rounds}",
        "curve": [(r["round"], r["psnr"]) for r in rounds],
        "steps": [r["steps"] for r in rounds],
        "kb_up": sum(ups) / len(ups) / 1e3 if ups else None,
        "planned": s.rounds,
    }


def baselines(run: Path) -> dict[str, list[dict]]:
    """The baselines' curves (``RUN/baselines/curves.json``): name -> [{steps, psnr}]."""
    path = run / "baselines" / "curves.json"
    return json.loads(path.read_text()) if path.exists() else {}


def at_steps(curve: list[dict], steps: int) -> float | None:
    """A baseline's PSNR at ``steps`` (None when it did not get there)."""
    return next((c["psnr"] for c in curve if c["steps"] == steps), None)


def report(rows: list[dict], base: dict[str, list[dict]], load: str) -> str:
    """Markdown table of the variants against the baselines at each variant's last round."""
    lines = [
        "# A swarm's federation: 4 drones, a shard per drone (what each drone saw)",
        "",
        "Swarm: `dronecap simulate --drones 4 --sensor aideck --frames 300` -> default ingest, "
        "sfm, split, `shard --scheme drone`. Global-model PSNR on all common test views after each "
        "round; baselines (centralized, each drone alone) on the same step budget. Made by "
        f"benchmarks/federated_swarm.py. Load average when the table was written: {load}.",
        "",
        "| exchange | schedule | kB up/drone/round | PSNR per round | last | best single "
        "| centralized | last - best single |",
        "|---|---|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        last_round, last = r["curve"][-1]
        steps = r["steps"][-1]
        singles = {k: at_steps(v, steps) for k, v in base.items() if k.startswith("client_")}
        singles = {k: v for k, v in singles.items() if v is not None}
        best = max(singles.values(), default=None)
        central = at_steps(base.get("centralized", []), steps)
        curve = " ".join(f"{p:.2f}" for _, p in r["curve"])
        if last_round < r["planned"]:
            curve += f" (stopped after round {last_round})"
        cells = [
            r["exchange"],
            r["schedule"],
            "-" if r["kb_up"] is None else f"{r['kb_up']:.1f}",
            curve,
            f"{last:.2f}",
            "-" if best is None else f"{best:.2f} ({max(singles, key=singles.get)})",
            "-" if central is None else f"{central:.2f}",
            "-" if best is None else f"{last - best:+.2f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "![PSNR per round](federated_swarm.png)", ""]
    return "\n".join(lines)


def plot(rows: list[dict], base: dict[str, list[dict]], path: Path) -> None:
    """PSNR against steps: one line per variant, the baselines dashed."""
    plt = pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for r in rows:
        ax.plot(r["steps"], [p for _, p in r["curve"]], "o-", label=r["exchange"])
    for name, curve in sorted(base.items()):
        ax.plot(
            [c["steps"] for c in curve],
            [c["psnr"] for c in curve],
            "s--" if name == "centralized" else ":",
            color="tab:red" if name == "centralized" else "gray",
            lw=1.2,
            label=name.replace("_", " ") + ("" if name == "centralized" else " alone"),
        )
    ax.set_xlabel("optimizer steps (coordinator's critical path)")
    ax.set_ylabel("test PSNR [dB]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    save_png(fig, path)


def main(argv: list[str] | None = None) -> int:
    """Tabulate the run folders given; the first holds the baselines."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+", help="federate run folders (first: baselines)")
    p.add_argument("--note", default="", help="a paragraph written under the table")
    a = p.parse_args(argv)
    rows = [load_run(r) for r in a.runs]
    base = baselines(a.runs[0])
    text = report(rows, base, " ".join(f"{x:.2f}" for x in os.getloadavg()))
    text += f"\n{a.note}\n" if a.note else ""
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    with atomic_output(RESULTS / "federated_swarm.md") as tmp:
        tmp.write_text(text)
    plot(rows, base, RESULTS / "federated_swarm.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
