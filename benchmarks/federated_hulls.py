"""Where a sector federation's quality goes: its global model's weights or its grid.

The server rebuilds the global model's occupancy grid inside the coordinator's visual hull
(``federated.run.rebuild_grid``: the server's trainer holds drone 0's shard only). On sector
shards that hull is carved by one sector's silhouettes, so it keeps cells that only the other
sectors' views would carve away, and the table's values there render as floaters in those
views. This diagnostic scores, on the same evenly spaced test views as
``benchmarks/federated_compression.py``:

- the global model of each round given, as the run recorded it (coordinator's hull);
- the same weights with a grid rebuilt inside the intersection of every drone's hull (what a
  centralized trainer carves from all the views; no process of the federation holds it today);
- with ``--drones``, each drone's own model after that round (its sector's data, its own grid)
  and the plain mean of the drones' weights (coordinator's hull);

and prints what one drone's hull costs to send (bits packed, deflated). A diagnostic of a
finished run folder (read only), no training:

    .venv/bin/python benchmarks/federated_hulls.py RUN --rounds 35 70 [--drones]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import zlib
from pathlib import Path

import numpy as np
from torch import Tensor

from dronecap.datasets.format import Dataset
from dronecap.federated import state as fed
from dronecap.federated.run import rebuild_grid
from dronecap.nerf import occupancy
from dronecap.nerf.trainer import Trainer


def settings(run: Path) -> fed.FedSettings:
    """The run's settings, ignoring keys of options since removed (e.g. session 16's
    ``feedback``)."""
    names = {f.name for f in dataclasses.fields(fed.FedSettings)}
    doc = json.loads((run / fed.SETTINGS).read_text())
    return fed.FedSettings(**{k: v for k, v in doc.items() if k in names})


def hull_intersection(run: Path, s: fed.FedSettings) -> Tensor:
    """The intersection of every drone's visual hull (bool tensor [R^3]); prints each hull's
    size and its bytes packed and deflated."""
    allowed = None
    for k, shard in enumerate(s.shards):
        own = Trainer.load(fed.round_file(fed.client_dir(run, k), 1), train=fed.train_split(shard))
        a = own.grid.allowed
        packed = np.packbits(a.cpu().numpy().reshape(-1)).tobytes()
        print(
            f"drone {k}: hull {int(a.sum())} cells, {len(packed)} B packed, "
            f"{len(zlib.compress(packed, 9))} B deflated"
        )
        allowed = a.clone() if allowed is None else allowed & a
    print(f"intersection: {int(allowed.sum())} cells")
    return allowed


def score_round(run: Path, s: fed.FedSettings, r: int, allowed: Tensor, test: Dataset) -> dict:
    """PSNR of round ``r``'s global model with the coordinator's hull and with ``allowed``."""
    g = Trainer.load(fed.round_file(run / "global", r), train=fed.train_split(s.shards[0]))
    out = {"global": g.evaluate(test)["psnr"]}
    g.grid = occupancy.restrict(g.grid, allowed)
    rebuild_grid(g)
    out["global, all hulls"] = g.evaluate(test)["psnr"]
    return out


def score_drones(run: Path, s: fed.FedSettings, r: int, test: Dataset) -> dict:
    """PSNR of each drone's own round-``r`` model (its own grid) and of the plain mean of
    their weights (grid rebuilt in the coordinator's hull, as the server does)."""
    out, weights = {}, []
    for k in range(s.n_clients):
        t = Trainer.load(fed.round_file(fed.client_dir(run, k), r))
        weights.append(t.model_weights())
        out[f"drone {k}"] = t.evaluate(test)["psnr"]
    g = Trainer.load(fed.round_file(run / "global", r), train=fed.train_split(s.shards[0]))
    g.load_model_weights({n: np.mean([w[n] for w in weights], axis=0) for n in weights[0]})
    rebuild_grid(g)
    out["plain mean"] = g.evaluate(test)["psnr"]
    return out


def main() -> None:
    """Run the diagnostic; see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("run", type=Path, help="a federated run folder (read only)")
    ap.add_argument("--rounds", type=int, nargs="+", required=True)
    ap.add_argument("--score-views", type=int, default=40)
    ap.add_argument("--drones", action="store_true", help="also score each drone's own model")
    a = ap.parse_args()
    s = settings(a.run)
    test = fed.test_split(s.shards[0], a.score_views)
    allowed = hull_intersection(a.run, s)
    for r in a.rounds:
        scores = score_round(a.run, s, r, allowed, test)
        if a.drones:
            scores |= score_drones(a.run, s, r, test)
        print(f"round {r}: " + ", ".join(f"{n} {v:.2f} dB" for n, v in scores.items()))


if __name__ == "__main__":
    main()
