"""A federated run's state on disk: its settings, per-drone and global checkpoints, the server
momentum and ``rounds.json`` (layout in :mod:`dronecap.federated.run`), and the modelled link
time of a round."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.format import Dataset, open_dataset
from dronecap.errors import InputError
from dronecap.files import atomic_output
from dronecap.nerf.config import TrainConfig, config_from_dict

SETTINGS = "federation.json"
ROUNDS = "rounds.json"
FINAL = "checkpoint.pt"
EVERY_CLIENT = -2  # fail_client value: every drone fails in fail_round (fault injection)


class FederationFailed(InputError):
    """A federation that cannot go on: every drone failed a round, or the pretraining failed.
    The rounds completed so far are kept; a rerun resumes from the last of them."""


@dataclass
class FedSettings:
    """One federated run. Paths are absolute; ``cfg`` is a TrainConfig as a dict."""

    shards: list[str]  # one dataset file per drone (kind "shard" or "dataset"), partition order
    cfg: dict[str, Any]
    pretrain: int  # N_pt: coordinator's steps before round 1
    local_steps: int  # N_l: steps per drone per round
    rounds: int  # R
    exchange_grid: bool = False  # also average the occupancy grid's densities
    transfer_dtype: str = "fp32"  # "fp32" or "fp16" for the floating arrays on the wire
    compress: bool = False  # lossless shuffle + deflate of every array on the wire (fedavg.py)
    quant_bits: int = 0  # 8 or 4: sparse quantised updates (sparse.py); 0: whole arrays
    mlp_bits: int = 8  # with quant_bits: bits of the MLPs' change (8 or 4); 8 = runs from before
    # the setting (session 13); new runs take `dronecap federate`'s default
    sparse_rows: float = 1.0  # with quant_bits: fraction of hash-table rows a drone sends
    down_rows: float = 0.0  # with quant_bits: fraction of table rows of the global model's
    # change broadcast each round (downlink.py); 0: the whole model is broadcast
    visibility: bool = False  # average each table row over the drones that sent it only
    server_lr: float = 1.0  # FedAvgM server step size (1 with momentum 0: plain FedAvg)
    server_momentum: float = 0.0  # FedAvgM server momentum
    table_step: str = "server"  # hash table: "server" step like the MLPs, or "mean" (lr 1)
    eval_views: int = 0  # test views for the per-round PSNR (0: all)
    round_timeout: float = 3600.0  # seconds the server waits for a round's replies
    fail_client: int = -1  # fault injection: this partition (EVERY_CLIENT: all) raises ...
    fail_round: int = -1  # ... in this round (-1: never)
    poison: dict[str, str] = field(default_factory=dict)  # fault injection: partition -> "nan",
    # "huge" (1e30 weights) or "count" (claims 10^9 images), in every round from 1 on
    seed: int = 0
    shard_sha256: list[str] = field(default_factory=list)  # content of each shard at the start

    def __post_init__(self) -> None:
        self.cfg = json.loads(json.dumps(self.cfg))  # tuples -> lists, as read back from disk

    @property
    def n_clients(self) -> int:
        """Number of drones."""
        return len(self.shards)

    @property
    def total_steps(self) -> int:
        """Steps on the coordinator's critical path: N_pt + R * N_l (the step budget)."""
        return self.pretrain + self.rounds * self.local_steps

    def train_config(self) -> TrainConfig:
        """The trainer configuration (its schedule spans the whole step budget)."""
        return config_from_dict(self.cfg).replace(steps=self.total_steps, seed=self.seed)


def save_settings(run_dir: Path, s: FedSettings) -> None:
    """Write ``RUN/federation.json`` atomically."""
    with atomic_output(run_dir / SETTINGS) as tmp:
        tmp.write_text(json.dumps(dataclasses.asdict(s), indent=1))


def load_settings(run_dir: Path) -> FedSettings:
    """Read ``RUN/federation.json``."""
    return FedSettings(**json.loads((Path(run_dir) / SETTINGS).read_text()))


def train_split(path: str | Path) -> Dataset:
    """The train images of one drone's shard file."""
    ds = open_dataset(path)
    return ds.subset(ds.indices("train"))


def test_split(path: str | Path, views: int = 0) -> Dataset:
    """The common test set carried by every shard (``views`` > 0: that many, evenly spaced)."""
    ds = open_dataset(path)
    idx = ds.indices("test")
    if 0 < views < len(idx):
        idx = idx[np.linspace(0, len(idx) - 1, views).round().astype(int)]
    return ds.subset(idx)


def client_dir(run_dir: Path, k: int) -> Path:
    """Folder of drone ``k``'s per-round checkpoints."""
    return Path(run_dir) / "clients" / f"client_{k}"


def round_file(folder: Path, r: int) -> Path:
    """``folder/round_RRR.pt``."""
    return Path(folder) / f"round_{r:03d}.pt"


def residual_file(folder: Path, r: int) -> Path:
    """``folder/residual_RRR.npz``: a drone's error-feedback residual after round ``r``."""
    return Path(folder) / f"residual_{r:03d}.npz"


def latest_round(folder: Path, before: int) -> int:
    """Highest round < ``before`` with a checkpoint in ``folder`` (-1: none)."""
    rounds = [int(p.stem[6:]) for p in Path(folder).glob("round_*.pt")]
    done = [r for r in rounds if r < before]
    return max(done, default=-1)


def save_momentum(run_dir: Path, r: int, momentum: dict[str, np.ndarray]) -> None:
    """Write the server optimizer's momentum after round ``r`` (``RUN/global/momentum_RRR.npz``;
    nothing when it has none)."""
    if momentum:
        with atomic_output(Path(run_dir) / "global" / f"momentum_{r:03d}.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **momentum)


def load_momentum(run_dir: Path, r: int) -> dict[str, np.ndarray]:
    """The momentum saved after round ``r`` (empty when none was saved)."""
    p = Path(run_dir) / "global" / f"momentum_{r:03d}.npz"
    if not p.exists():
        return {}
    with np.load(p) as z:
        return {k: z[k] for k in z.files}


def link_time(n_bytes: int) -> float | None:
    """Modelled seconds to send ``n_bytes`` over the drone radio (the GAP9 cost model's link);
    None while that model is not installed."""
    try:
        from dronecap.gap9.model import link_time_s
    except ImportError:
        return None
    return float(link_time_s(n_bytes))


AIDECK_WIFI_BYTES_PER_S = 8 * 320 * 240  # the AI-deck's stock Wi-Fi streamer: 8 raw QVGA
# frames/s with one drone on the router (about 6 each with two): ~614 kB/s for the whole swarm,
# not the radio's rated 15 Mbit/s (docs/federated.md; a federated constant, not a GAP9 one)


def round_link_times(entry: dict) -> dict[str, float | None]:
    """Modelled link seconds of a round, every upload and download in turn over one shared
    channel (as the paper counts it: 4 x 0.52 MB each way -> 2.24 s at 15 Mbit/s):
    ``link_s`` at the GAP9 model's rated radio, ``wifi_s`` at the AI-deck's measured Wi-Fi
    throughput (:data:`AIDECK_WIFI_BYTES_PER_S`, shared by the swarm)."""
    n = sum(entry["bytes_up"].values()) + sum(entry["bytes_down"].values())
    return {"link_s": link_time(n), "wifi_s": n / AIDECK_WIFI_BYTES_PER_S}


def load_rounds(run_dir: Path) -> list[dict]:
    """Completed rounds recorded in ``RUN/rounds.json`` (empty when none)."""
    p = Path(run_dir) / ROUNDS
    return json.loads(p.read_text())["rounds"] if p.exists() else []


def save_rounds(run_dir: Path, s: FedSettings, history: list[dict], **extra: Any) -> None:
    """Rewrite ``RUN/rounds.json`` atomically (settings, rounds, and any ``extra`` sections)."""
    p = Path(run_dir) / ROUNDS
    doc = json.loads(p.read_text()) if p.exists() else {}
    doc.update(settings=dataclasses.asdict(s), rounds=history, **extra)
    with atomic_output(p) as tmp:
        tmp.write_text(json.dumps(doc, indent=1))
