"""Compressed federated rounds on lego: bytes per drone per round each way, PSNR after R rounds,
the gap to a centralized model and to the best single drone, on the same step budget.

lego 160x160 RGB, K drones (``dronecap shard``, IID and sector), the scene-sized model resolved
once on the union of the shards (as ``dronecap federate`` does), Flower's simulation engine.
Variants, each a whole federation from the same seed; they share round 0 (the coordinator's
pretraining does not depend on the exchange: the first variant's is copied into the others), so
their differences are the rounds' alone:

- ``fp16 M``: every array whole in fp16 both ways, FedAvgM server step (lr 2, momentum 0.5)
  (session 10's reference); ``fp16``: the same with plain FedAvg
  (the paper's exchange);
- ``q4 r3 M``: uploads are 4-bit changes of the 3 % most changed hash-table rows (MLPs 8-bit,
  error feedback), plain row averaging, whole fp16 downloads;
- ``q4 r3 vis M``: the same with visibility-weighted row averaging (session 9's default);
- ``default``: what ``dronecap federate`` does without flags (read from its settings; since
  session 11 the hash table takes the drones' mean change, ``--table-step mean``), and
  ``fp16 default``: the same aggregation on whole fp16 arrays (the reference the default's
  compression is held to);
- ``default d5``: the default plus sparse downloads of 5 % of the table rows (``--down-rows
  0.05``);
- ``q4 r3 vis M dF``: plus sparse downloads (the global model's change, F % of the table rows
  at 4 bits, MLPs 8-bit; each drone keeps its copy);

plus, on the same step budget N_pt + R N_l, a centralized model on the union of the shards and
every drone alone (``--singles``). Every final model (each variant's global model, the
baselines) is scored on the same ``--score-views`` evenly spaced test views. Bytes are what
Flower serialises (``rounds.json``, median over drones and rounds 1..R).

Sized for a shared 2-core machine (a few minutes per federation with the defaults below):

    .venv/bin/python benchmarks/federated_compression.py --work /tmp/fedcomp

Writes benchmarks/results/<--results>.md and .png.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shutil
import statistics
import time
from pathlib import Path

from dronecap.datasets.blender import import_blender
from dronecap.datasets.shard import shard_dataset
from dronecap.federated import engines
from dronecap.federated import state as fed
from dronecap.federated.baselines import run_baselines
from dronecap.federated.sizing import resolve_once
from dronecap.files import atomic_output
from dronecap.nerf.config import preset
from dronecap.plots import pyplot

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_160" / "lego"
RESULTS = REPO / "benchmarks" / "results"
SERVER_STEP = dict(server_lr=2.0, server_momentum=0.5)
SPARSE_UP = dict(quant_bits=4, sparse_rows=0.03)


def _cli_default() -> dict:
    """The exchange ``dronecap federate`` uses without flags (read from its settings)."""
    from dronecap.commands.federate import Settings

    d = Settings()
    names = (
        "quant_bits",
        "mlp_bits",
        "sparse_rows",
        "down_rows",
        "server_lr",
        "server_momentum",
        "table_step",
    )
    return dict(visibility=not d.plain_average, **{n: getattr(d, n) for n in names})


DEFAULT = _cli_default()
VARIANTS: dict[str, dict] = {  # in the order they run: the reference first
    "fp16 M": dict(quant_bits=0, **SERVER_STEP),
    "fp16 default": {**DEFAULT, "quant_bits": 0},  # the default's aggregation, whole fp16 arrays
    "default": DEFAULT,
    "default d5": {**DEFAULT, "down_rows": 0.05},  # plus sparse downloads, 5 % of the rows
    "q4 r3 vis M": dict(**SPARSE_UP, visibility=True, **SERVER_STEP),
    "q4 r3 vis M d5": dict(**SPARSE_UP, visibility=True, down_rows=0.05, **SERVER_STEP),
    "q4 r3 vis M d10": dict(**SPARSE_UP, visibility=True, down_rows=0.10, **SERVER_STEP),
    "q4 r3 M": dict(**SPARSE_UP, **SERVER_STEP),
    "fp16": dict(quant_bits=0),
}
REFERENCE = "fp16 default"


def main() -> None:
    """Run the benchmark; see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/fedcomp"))
    ap.add_argument("--pretrain", type=int, default=500)
    ap.add_argument("--local-steps", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--drones", type=int, nargs="+", default=[4])
    ap.add_argument("--eval-views", type=int, default=4, help="test views per round")
    ap.add_argument("--score-views", type=int, default=40, help="test views of the final scores")
    ap.add_argument("--schemes", nargs="+", default=["iid", "sector"])
    ap.add_argument("--seed", type=int, default=0, help="seed of every training (not the shards)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--singles", action="store_true", help="also train every drone alone")
    ap.add_argument("--results", default="federated_compression")
    ap.add_argument(
        "--only",
        choices=("federated", "baselines"),
        help="run only the federations or only the baselines (processes side by side), then "
        "tabulate what --work holds",
    )
    ap.add_argument("--report", action="store_true", help="run nothing: tabulate --work's runs")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    lego = a.work / "lego.h5"
    if not lego.exists():
        import_blender(LEGO, lego, progress=False)
    a.load = [os.getloadavg()]
    rows = []
    for drones in a.drones:
        for scheme in a.schemes:
            rows += _scheme(a, lego, drones, scheme)
            _write(a, rows)  # after every scheme: a partial table survives an interruption


def _settings(a: argparse.Namespace, paths: list[Path], cfg: dict, variant: str) -> fed.FedSettings:
    return fed.FedSettings(
        shards=[str(p) for p in paths],
        cfg=cfg,
        pretrain=a.pretrain,
        local_steps=a.local_steps,
        rounds=a.rounds,
        transfer_dtype="fp16",
        eval_views=a.eval_views,
        seed=a.seed,
        **VARIANTS[variant],
    )


def _scheme(a: argparse.Namespace, lego: Path, drones: int, scheme: str) -> list[dict]:
    """Run (or, with ``--report``, only read) every variant and the baselines of one scheme
    and swarm size; returns the table rows."""
    shards = a.work / f"shards_{scheme}_{drones}"
    if not (shards / "summary.json").exists():
        shard_dataset(lego, shards, drones, scheme)
    paths = [shards / f"client_{k}.h5" for k in range(drones)]
    cfg = dataclasses.asdict(resolve_once(preset("scene-sized"), paths).config)
    folder = {n: a.work / f"{scheme}_{drones}_{n.replace(' ', '_')}" for n in VARIANTS}
    for name in a.variants:
        run, first = folder[name], folder[a.variants[0]]  # the first variant pretrains
        s = _settings(a, paths, cfg, name)
        if not a.report and a.only != "baselines":
            run.mkdir(parents=True, exist_ok=True)
            fed.save_settings(run, s)
            if run != first and fed.load_rounds(first) and not fed.load_rounds(run):
                _copy_pretraining(first, run, s)
            done = fed.load_rounds(run)
            t0 = time.perf_counter()
            if not done or done[-1]["round"] < a.rounds:
                _simulate(run)
            print(f"{run.name}: {time.perf_counter() - t0:.0f} s, load {os.getloadavg()}")
            a.load.append(os.getloadavg())
    ran = {n: folder[n] for n in a.variants if len(fed.load_rounds(folder[n])) > 1}
    common = min((fed.load_rounds(run)[-1]["round"] for run in ran.values()), default=0)
    rows = [_row(a, scheme, drones, n, run, common) for n, run in ran.items()]
    base = a.work / f"baselines_{scheme}_{drones}"
    names = ["centralized"] + ([f"client_{k}" for k in range(drones)] if a.singles else [])
    if not a.report and a.only != "federated":
        base.mkdir(parents=True, exist_ok=True)
        run_baselines(base, _settings(a, paths, cfg, REFERENCE), curve_marks=False, names=names)
    scores = {n: _score(a, base / "baselines" / f"{n}.pt", paths[0]) for n in names}
    for r in rows:
        if r["rounds"] < a.rounds:  # a stopped run: the baselines' budget is not its own
            scores = {n: float("nan") for n in scores}
        r["central"] = scores.get("centralized", float("nan"))
        singles = {n: v for n, v in scores.items() if n != "centralized"}
        r["single"], r["single_name"] = (
            max((v, n) for n, v in singles.items()) if singles else (float("nan"), "")
        )
    return rows


def _simulate(run: Path, attempts: int = 3) -> None:
    """Run (or resume) a federation; Ray's start-up gives up after 30 s, which a loaded
    machine exceeds: try again (the run resumes after its last recorded round)."""
    for attempt in range(attempts):
        try:
            engines.run_simulated(run, engines.SimulationResources(total_cpus=2))
            return
        except RuntimeError as err:
            if attempt == attempts - 1:
                raise
            print(f"{run.name}: {err}; trying again")


def _copy_pretraining(src: Path, dst: Path, s: fed.FedSettings) -> None:
    """Round 0 of ``src`` (the coordinator's pretraining, its checkpoint and rounds.json entry)
    as round 0 of ``dst``."""
    for rel in ("global/round_000.pt", "clients/client_0/round_000.pt"):
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(src / rel, dst / rel)
    fed.save_rounds(dst, s, fed.load_rounds(src)[:1])


def _score(a: argparse.Namespace, checkpoint: Path, shard: Path) -> float:
    """PSNR of a saved model on ``--score-views`` evenly spaced test views (nan: missing)."""
    from dronecap.nerf.trainer import Trainer

    if not checkpoint.exists():
        return float("nan")
    return float(Trainer.load(checkpoint).evaluate(fed.test_split(shard, a.score_views))["psnr"])


def _row(a: argparse.Namespace, scheme: str, drones: int, name: str, run: Path, last: int) -> dict:
    """One table row from a run's rounds 1..``last`` (round 0 is the pretraining: not
    counted); its PSNR is the global model's after round ``last`` (the last round every
    variant of the scheme reached, when some were stopped)."""
    rounds = fed.load_rounds(run)[: last + 1]
    model = fed.round_file(run / "global", last)
    up = [b for r in rounds[1:] for b in r["bytes_up"].values()]
    down = [b for r in rounds[1:] for b in r["bytes_down"].values()]
    return dict(
        scheme=scheme,
        drones=drones,
        variant=name,
        up=statistics.median(up),
        down=statistics.median(down),
        down_max=max(down),
        wifi=statistics.median(r["wifi_s"] for r in rounds[1:]),
        psnr=_score(a, model, Path(fed.load_settings(run).shards[0])),
        rounds=rounds[-1]["round"],
        left_out=sum(len(r["failed"]) for r in rounds),
        wall=sum(r["wall_s"] for r in rounds),
    )


def _write(a: argparse.Namespace, rows: list[dict]) -> None:
    """Print the table and write RESULTS/<results>.md and .png."""
    ref = {(r["scheme"], r["drones"]): r["psnr"] for r in rows if r["variant"] == REFERENCE}
    loads = ", ".join(f"{x[0]:.1f}" for x in a.load)
    lines = [
        "# Compressed federated rounds (benchmarks/federated_compression.py)",
        "",
        f"lego 160 px, scene-sized model resolved on the shards, N_pt = {a.pretrain}, "
        f"N_l = {a.local_steps}, R = {a.rounds} ({a.pretrain + a.rounds * a.local_steps} steps "
        "on every method's critical path: a short schedule for a shared 2-core machine, PSNRs "
        "are far below converged ones; compare rows of one scheme and swarm size). PSNR of "
        "each global model after the round given (R, or the last round every variant of the "
        "scheme reached when runs were stopped; baselines only at R) and of the baselines, on "
        f"the same {a.score_views} evenly spaced test views; bytes as Flower serialises them, "
        "median over drones and rounds (down max: round 1's whole model); Wi-Fi s: one round's "
        "uploads and downloads in turn at the AI-deck's ~614 kB/s; wall: the run's rounds. "
        f"1-minute load average when this table was written: {loads}.",
        "",
        f"Command: `.venv/bin/python benchmarks/federated_compression.py --work {a.work} "
        f"--pretrain {a.pretrain} --local-steps {a.local_steps} --rounds {a.rounds} "
        f"--drones {' '.join(map(str, a.drones))} --schemes {' '.join(a.schemes)} "
        f"--score-views {a.score_views} --variants {' '.join(repr(v) for v in a.variants)} "
        f"--seed {a.seed} --results {a.results}{' --singles' if a.singles else ''}"
        f"{' --only ' + a.only if a.only else ''}`",
        "",
        "| scheme | drones | variant | rounds | up B/drone/round | down B/drone/round | down max | "
        f"Wi-Fi s/round | PSNR dB | vs {REFERENCE} | vs central | vs best single | wall s |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        vs = r["psnr"] - ref.get((r["scheme"], r["drones"]), float("nan"))
        lines.append(
            f"| {r['scheme']} | {r['drones']} | {r['variant']} | {r['rounds']} | {r['up']:,.0f} | "
            f"{r['down']:,.0f} | {r['down_max']:,.0f} | {r['wifi']:.2f} | {r['psnr']:.2f} | "
            f"{_signed(vs)} | {_signed(r['psnr'] - r['central'])} | "
            f"{_signed(r['psnr'] - r['single'])} | "
            f"{r['wall']:.0f} |"
        )
    central = {
        (r["scheme"], r["drones"]): (r["central"], r["single"], r["single_name"]) for r in rows
    }
    lines += [
        "",
        "| scheme | drones | centralized dB | best single drone dB |",
        "|---|---:|---:|---|",
    ]
    for (scheme, drones), (c, b, n) in central.items():
        lines.append(f"| {scheme} | {drones} | {_signed(c, '.2f')} | {_signed(b, '.2f')} {n} |")
    text = "\n".join(lines) + "\n"
    print(text)
    with atomic_output(RESULTS / f"{a.results}.md") as tmp:
        tmp.write_text(text)
    _figure(rows, ref, RESULTS / f"{a.results}.png")


def _signed(value: float, fmt: str = "+.2f") -> str:
    """A table cell: the value, or a dash when its baseline did not run (nan)."""
    return "—" if math.isnan(value) else format(value, fmt)


def _figure(rows: list[dict], ref: dict, path: Path) -> None:
    """PSNR minus the reference's vs bytes per drone per round (up and down); nothing when the
    reference variant did not run (the figure would be empty)."""
    plt = pyplot()
    if plt is None or not ref:
        return
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (scheme, drones), psnr in ref.items():
        mine = [r for r in rows if (r["scheme"], r["drones"]) == (scheme, drones)]
        x = [r["up"] + r["down"] for r in mine]
        y = [r["psnr"] - psnr for r in mine]
        ax.scatter(x, y, label=f"{scheme}, {drones} drones")
        for r, xi, yi in zip(mine, x, y, strict=True):
            ax.annotate(r["variant"], (xi, yi), fontsize=7)
    ax.axhline(-0.2, color="grey", ls=":", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("bytes up + down per drone per round (as Flower serialises them)")
    ax.set_ylabel(f"PSNR after round R - {REFERENCE} (dB)")
    ax.legend()
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


if __name__ == "__main__":
    main()
