"""Compressed federated updates on lego: bytes per drone per round and PSNR after R rounds.

lego 160x160 RGB, 4 drones (``dronecap shard``, IID and sector), the scene-sized model resolved
once on the union of the shards (as ``dronecap federate`` does), Flower's simulation engine.
Variants, each a whole federation from the same seed and pretraining schedule:

- ``fp16``: every array whole in fp16 (the reference exchange);
- ``q8``: every array's change 8-bit with per-block scales, all rows;
- ``q8 r10``: 8-bit, only the 10 % most changed hash-table rows (error feedback);
- ``q4 r3``: 4-bit, 3 % of the rows; ``q4 r3 M``: the same with a FedAvgM server step
  (lr 2, momentum 0.5);
- ``q4 r3 vis M``: the same, rows averaged over the drones that sent them (visibility): the
  default of ``dronecap federate``;
- ``fp16 M``: whole fp16 arrays with that server step;

plus a centralized model on the union of the shards with the same step budget. Bytes are what
Flower serialises (``rounds.json``: ``bytes_up`` per drone, median over rounds 1..R).

Sized for a shared 2-core machine (a few minutes per federation with the defaults below):

    nice .venv/bin/python benchmarks/federated_compression.py --work /tmp/fedcomp

Writes benchmarks/results/federated_compression.md and .png.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
from pathlib import Path

from dronecap.datasets.blender import import_blender
from dronecap.datasets.shard import shard_dataset
from dronecap.federated import engines
from dronecap.federated import state as fed
from dronecap.federated.baselines import load_curves, run_baselines
from dronecap.federated.sizing import resolve_once
from dronecap.files import atomic_output
from dronecap.nerf.config import preset
from dronecap.plots import pyplot

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"
RESULTS = REPO / "benchmarks" / "results"
VARIANTS: dict[str, dict] = {  # in the order they run: the reference and the default first
    "fp16": dict(quant_bits=0),
    "q4 r3 vis M": dict(
        quant_bits=4, sparse_rows=0.03, visibility=True, server_lr=2.0, server_momentum=0.5
    ),
    "fp16 M": dict(quant_bits=0, server_lr=2.0, server_momentum=0.5),
    "q4 r3 M": dict(quant_bits=4, sparse_rows=0.03, server_lr=2.0, server_momentum=0.5),
    "q4 r3": dict(quant_bits=4, sparse_rows=0.03),
    "q8": dict(quant_bits=8, sparse_rows=1.0),
    "q8 r10": dict(quant_bits=8, sparse_rows=0.10),
}


def main() -> None:
    """Run the benchmark; see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/fedcomp"))
    ap.add_argument("--pretrain", type=int, default=300)
    ap.add_argument("--local-steps", type=int, default=25)
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--drones", type=int, default=4)
    ap.add_argument("--eval-views", type=int, default=8)
    ap.add_argument("--schemes", nargs="+", default=["iid", "sector"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--results", default="federated_compression")
    ap.add_argument(
        "--report",
        action="store_true",
        help="run nothing: tabulate the runs in --work at the last round all of a scheme's "
        "variants reached (a benchmark stopped early)",
    )
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    lego = a.work / "lego.h5"
    if not lego.exists():
        import_blender(LEGO, lego, progress=False)
    rows = []
    for scheme in a.schemes:
        shards = a.work / f"shards_{scheme}_{a.drones}"
        if not (shards / "summary.json").exists():
            shard_dataset(lego, shards, a.drones, scheme)
        if a.report:
            rows += _reported(a, scheme)
            continue
        paths = [shards / f"client_{k}.h5" for k in range(a.drones)]
        cfg = dataclasses.asdict(resolve_once(preset("scene-sized"), paths).config)
        central = None
        for name in a.variants:
            run = a.work / f"{scheme}_{a.drones}_{name.replace(' ', '_')}"
            s = fed.FedSettings(
                shards=[str(p) for p in paths],
                cfg=cfg,
                pretrain=a.pretrain,
                local_steps=a.local_steps,
                rounds=a.rounds,
                transfer_dtype="fp16",
                eval_views=a.eval_views,
                **VARIANTS[name],
            )
            run.mkdir(parents=True, exist_ok=True)
            fed.save_settings(run, s)
            done = fed.load_rounds(run)
            if not done or done[-1]["round"] < a.rounds:
                engines.run_simulated(run, engines.SimulationResources(total_cpus=2))
            if central is None:
                if not (run / "baselines" / "curves.json").exists():
                    run_baselines(run, s, curve_marks=False, names=["centralized"])
                central = load_curves(run)["centralized"][-1]["psnr"]
            rows.append(_row(scheme, name, fed.load_rounds(run), central))
            _write(a, rows)  # after every run: a partial table survives an interruption
    if a.report:
        _write(a, rows)


def _reported(a: argparse.Namespace, scheme: str) -> list[dict]:
    """Rows of the finished or stopped runs of ``scheme`` in ``a.work``, all cut at the last
    round every one of them recorded (runs without a completed round 1 are left out)."""
    runs = {n: a.work / f"{scheme}_{a.drones}_{n.replace(' ', '_')}" for n in a.variants}
    done = {n: fed.load_rounds(r) for n, r in runs.items() if (r / fed.ROUNDS).exists()}
    done = {n: rounds for n, rounds in done.items() if len(rounds) > 1}
    if not done:
        return []
    last = min(rounds[-1]["round"] for rounds in done.values())
    central = float("nan")
    for r in runs.values():
        if (r / "baselines" / "curves.json").exists():
            central = load_curves(r)["centralized"][-1]["psnr"]
    return [_row(scheme, n, rounds[: last + 1], central) for n, rounds in done.items()]


def _row(scheme: str, name: str, rounds: list[dict], central: float) -> dict:
    """One table row from a run's rounds (round 0 is the pretraining: not counted)."""
    up = [b for r in rounds[1:] for b in r["bytes_up"].values()]
    down = [b for r in rounds[1:] for b in r["bytes_down"].values()]
    return dict(
        scheme=scheme,
        variant=name,
        up=statistics.median(up),
        down=statistics.median(down),
        wifi=statistics.median(r["wifi_s"] for r in rounds[1:]),
        psnr=rounds[-1]["psnr"],
        rounds=rounds[-1]["round"],
        central=central,
        left_out=sum(len(r["failed"]) for r in rounds),
    )


def _write(a: argparse.Namespace, rows: list[dict]) -> None:
    """Print the table and write RESULTS/<results>.md and .png."""
    ref = {r["scheme"]: r["psnr"] for r in rows if r["variant"] == "fp16"}
    lines = [
        "# Compressed federated updates (benchmarks/federated_compression.py)",
        "",
        f"lego 160 px, {a.drones} drones, scene-sized model resolved on the shards, "
        f"N_pt = {a.pretrain}, N_l = {a.local_steps}, R = {a.rounds} (a short schedule for a "
        f"shared 2-core machine: PSNRs are far below converged ones; compare rows of one scheme), "
        f"PSNR on {a.eval_views} evenly spaced test views after the round given (R, or fewer "
        "when the run was stopped: `--report` compares a scheme's variants at one round); "
        "bytes as Flower serialises them, median over drones and rounds 1..R; Wi-Fi s: one "
        "round's uploads and downloads in turn at the AI-deck's ~614 kB/s. Load average: "
        f"{' '.join(os.getloadavg().__repr__().strip('()').split(', '))}.",
        "",
        f"Command: `nice .venv/bin/python benchmarks/federated_compression.py --work {a.work} "
        f"--pretrain {a.pretrain} --local-steps {a.local_steps} --rounds {a.rounds} "
        f"--drones {a.drones} --eval-views {a.eval_views}`",
        "",
        "| scheme | variant | rounds | up B/drone/round | down B/drone/round | Wi-Fi s/round "
        "| PSNR dB | vs fp16 dB | vs central dB |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        vs = r["psnr"] - ref.get(r["scheme"], float("nan"))
        lines.append(
            f"| {r['scheme']} | {r['variant']} | {r['rounds']} | {r['up']:,.0f} | "
            f"{r['down']:,.0f} | {r['wifi']:.2f} | {r['psnr']:.2f} | {vs:+.2f} | "
            f"{r['psnr'] - r['central']:+.2f} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    with atomic_output(RESULTS / f"{a.results}.md") as tmp:
        tmp.write_text(text)
    _figure(rows, RESULTS / f"{a.results}.png")


def _figure(rows: list[dict], path: Path) -> None:
    """PSNR after round R minus the fp16 exchange's vs bytes up per drone per round."""
    plt = pyplot()
    if plt is None:
        return
    ref = {r["scheme"]: r["psnr"] for r in rows if r["variant"] == "fp16"}
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for scheme, marker in (("iid", "o"), ("sector", "s")):
        mine = [r for r in rows if r["scheme"] == scheme]
        if scheme not in ref:
            continue
        ax.scatter(
            [r["up"] for r in mine],
            [r["psnr"] - ref[scheme] for r in mine],
            marker=marker,
            label=scheme,
        )
        for r in mine:
            ax.annotate(r["variant"], (r["up"], r["psnr"] - ref[scheme]), fontsize=7)
    ax.axvline(25_000, color="grey", ls="--", lw=0.8)
    ax.axhline(-0.2, color="grey", ls=":", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("bytes up per drone per round (as Flower serialises them)")
    ax.set_ylabel("PSNR after round R - fp16 exchange (dB)")
    ax.legend()
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


if __name__ == "__main__":
    main()
