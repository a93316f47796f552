"""Federated Tiny-DroNeRF on Flower: the settings, the ClientApp (one per drone), the ServerApp.

The same two apps run under Flower's simulation engine (Ray) and in deployment mode
(``flower-superlink`` + one ``flower-supernode`` per drone, ``flwr run``; both in
:mod:`dronecap.federated.engines`, see docs/federated.md). Everything a process needs is in
the run directory, so a ClientApp may run in a fresh process for every message and an
interrupted run resumes where it stopped:

    RUN/federation.json              settings (shards, config, schedule) -- written by the driver
    RUN/clients/client_K/round_RRR.pt  drone K's trainer after round RRR (weights, grid, Adam)
    RUN/global/round_RRR.pt          global model after round RRR (round 0 = coordinator's pretrain)
    RUN/global/momentum_RRR.npz      server momentum after round RRR (FedAvgM runs only)
    RUN/rounds.json                  per-round PSNR, bytes per direction, link time, failures
    RUN/checkpoint.pt                final global model (``Trainer.load``-able)

Protocol (rounds numbered from 1; round 0 is the pretraining):
 1. ``query``: every drone reports its partition id and train-image count.
 2. ``train.pretrain`` to the coordinator (partition 0): ``pretrain`` steps from scratch; its
    model is the initial global model.
 3. each round, ``train`` to all drones (Flower's FedAvg ``configure_train``): load the global
    model (and the averaged grid with ``exchange_grid``), train ``local_steps``, save the local
    checkpoint, reply with the update; the server averages (``DroneFedAvg``) and tests the
    global model on the common test set.

Non-averaged state stays with the drone across rounds: its occupancy grid (unless exchanged) and
its Adam moments and step counter (never reset: a drone's optimizer continues from its previous
round, only the parameters are replaced by the global ones). A drone that raises or does not
reply within ``round_timeout`` is left out of that round's average; next round it continues
from its last checkpoint. A round where every drone failed raises :class:`FederationFailed`
(never a round recorded with the old model); the rounds before it stay recorded.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from flwr.app import ConfigRecord, Context, Message, MessageType, MetricRecord, RecordDict
from flwr.clientapp import ClientApp
from flwr.serverapp import Grid, ServerApp

from dronecap.datasets.format import Dataset, open_dataset
from dronecap.errors import InputError
from dronecap.federated.fedavg import (
    WEIGHT_KEY,
    DroneFedAvg,
    from_record,
    pack_update,
    payload_bytes,
    to_record,
    unpack_update,
)
from dronecap.files import atomic_output
from dronecap.nerf.config import TrainConfig, config_from_dict

log = logging.getLogger("dronecap.federate")

SETTINGS = "federation.json"
ROUNDS = "rounds.json"
FINAL = "checkpoint.pt"
PRETRAIN_ACTION = f"{MessageType.TRAIN}.pretrain"
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
    server_lr: float = 1.0  # FedAvgM server step size (1 with momentum 0: plain FedAvg)
    server_momentum: float = 0.0  # FedAvgM server momentum
    eval_views: int = 0  # test views for the per-round PSNR (0: all)
    round_timeout: float = 3600.0  # seconds the server waits for a round's replies
    fail_client: int = -1  # fault injection: this partition (EVERY_CLIENT: all) raises ...
    fail_round: int = -1  # ... in this round (-1: never)
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


def latest_round(folder: Path, before: int) -> int:
    """Highest round < ``before`` with a checkpoint in ``folder`` (-1: none)."""
    rounds = [int(p.stem[6:]) for p in Path(folder).glob("round_*.pt")]
    done = [r for r in rounds if r < before]
    return max(done, default=-1)


# ----------------------------------------------------------------------------------------------
# ClientApp: one drone
# ----------------------------------------------------------------------------------------------

clientapp = ClientApp()


@clientapp.query()
def _describe(msg: Message, context: Context) -> Message:
    """Reply with this drone's partition id and train-image count."""
    k = int(context.node_config["partition-id"])
    s = load_settings(Path(str(msg.content["config"]["run-dir"])))
    n = len(open_dataset(s.shards[k]).indices("train"))
    return Message(
        RecordDict({"info": MetricRecord({"partition-id": k, WEIGHT_KEY: n})}), reply_to=msg
    )


@clientapp.train("pretrain")
def _pretrain(msg: Message, context: Context) -> Message:
    """The coordinator's pretraining (round 0): train from scratch, reply with the model."""
    return _local_round(msg, context, pretrain=True)


@clientapp.train()
def _train(msg: Message, context: Context) -> Message:
    """One round on this drone: load the global model, train N_l steps, reply with the update."""
    return _local_round(msg, context, pretrain=False)


def _local_round(msg: Message, context: Context, pretrain: bool) -> Message:
    from dronecap.nerf.trainer import Trainer

    config = msg.content["config"]
    run_dir = Path(str(config["run-dir"]))
    s = load_settings(run_dir)
    k = int(context.node_config["partition-id"])
    r = 0 if pretrain else int(config["server-round"])
    if r == s.fail_round and s.fail_client in (k, EVERY_CLIENT):
        raise RuntimeError(f"injected fault: client {k} fails in round {r}")
    train = train_split(s.shards[k])
    folder = client_dir(run_dir, k)
    prev = latest_round(folder, r)
    if prev >= 0:
        trainer = Trainer.load(round_file(folder, prev), train=train)
    else:
        trainer = Trainer(s.train_config(), train)
    if not pretrain:
        install_global(trainer, from_record(msg.content["arrays"]), rebuild=prev < 0)
        if prev < 0:
            trainer.step = s.pretrain  # join the coordinator's learning-rate schedule
    t0 = time.perf_counter()
    trainer.train(s.pretrain if pretrain else s.local_steps)
    train_s = time.perf_counter() - t0
    with atomic_output(round_file(folder, r)) as tmp:
        trainer.save(tmp)
    arrays = pack_update(
        trainer.model_weights(),
        trainer.grid_state() if s.exchange_grid else None,
        s.transfer_dtype,
    )
    metrics = MetricRecord({WEIGHT_KEY: train.n, "train-s": train_s, "partition-id": k})
    record = to_record(arrays, s.compress)
    return Message(RecordDict({"arrays": record, "metrics": metrics}), reply_to=msg)


def install_global(trainer: Any, update: dict[str, np.ndarray], rebuild: bool) -> None:
    """Load a received global update into ``trainer``.

    The model weights are replaced. An exchanged grid (its densities [R^3]) replaces the local
    one, occupancy re-thresholded as the grid update does (``density > min(thr, mean)``);
    otherwise, with ``rebuild``, the grid is rebuilt from the new model's own densities (a drone
    without a grid of its own, or the server's copy of the global model), else the local grid
    is kept.
    """
    model, grid = unpack_update(update)
    trainer.load_model_weights(model)
    if grid:
        density = np.asarray(grid["density"], np.float32)
        thr = min(trainer.cfg.grid_threshold, float(density.mean()))
        trainer.load_grid_state({"density": density, "occupied": density > thr})
    elif rebuild:
        rebuild_grid(trainer)


REBUILD_PASSES = 16  # full grid updates when a grid is rebuilt from a model alone


def rebuild_grid(trainer: Any, passes: int = REBUILD_PASSES) -> None:
    """Replace ``trainer``'s occupancy grid by one computed from its current model alone.

    ``passes`` warm-up-style updates of every cell from an empty grid, each at one random
    point per cell: a cell ends with about the largest optical thickness seen at ``passes``
    points. One pass is not enough: thin parts whose cell was probed at an empty point
    vanish from the render. On the lego IID benchmark the global model scored 25.38 dB with
    one pass, 26.07 with 4 and 26.14 with 16 (the centralized model: 26.12), on 20 views.
    """
    from dronecap.nerf import occupancy

    grid = occupancy.init_state(trainer.grid_cfg, trainer.device)
    for _ in range(passes):
        grid = occupancy.update(
            trainer.grid_cfg,
            grid,
            0,
            trainer.field.density,
            trainer.aabb,
            trainer.step_size,
            trainer.generator,
        )
    trainer.grid = grid


# ----------------------------------------------------------------------------------------------
# ServerApp: the coordinator's aggregation and the per-round test
# ----------------------------------------------------------------------------------------------


def make_server_app(run_dir: str | Path | None = None) -> ServerApp:
    """The ServerApp of a run; ``run_dir`` None: taken from the run config key ``run-dir``."""
    app = ServerApp()

    @app.main()
    def _main(grid: Grid, context: Context) -> None:
        serve(grid, Path(run_dir or str(context.run_config["run-dir"])))

    return app


serverapp = make_server_app()  # deployment: `flwr run` passes run-dir in the run config


def serve(grid: Grid, run_dir: Path) -> None:
    """Run (or resume) the federation whose settings are in ``run_dir``; see the module doc."""
    s = load_settings(run_dir)
    history = load_rounds(run_dir)
    evaluator = GlobalEvaluator(s)
    nodes = _discover(grid, s, run_dir)
    if not history:
        t0 = time.perf_counter()
        msg = _message(grid, nodes[0], PRETRAIN_ACTION, ConfigRecord({"run-dir": str(run_dir)}))
        (reply,) = list(grid.send_and_receive([msg], timeout=s.round_timeout))
        if reply.has_error():
            reason = _last_line(reply.error.reason)
            raise FederationFailed(f"the coordinator's pretraining failed: {reason}", run_dir)
        update = from_record(reply.content["arrays"])
        entry = {"round": 0, "bytes_up": {"0": payload_bytes(reply.content)}, "bytes_down": {}}
        history.append(evaluator.finish_round(run_dir, 0, update, entry, t0))
        save_rounds(run_dir, s, history)
    strategy = DroneFedAvg(
        min_train_nodes=s.n_clients,
        min_available_nodes=s.n_clients,
        arrayrecord_key="arrays",
        server_learning_rate=s.server_lr,
        server_momentum=s.server_momentum,
    )
    part = {node: k for k, node in nodes.items()}
    last = history[-1]["round"]
    current = pack_update(*evaluator.load_global(run_dir, last), "fp32")
    strategy.resume(current, load_momentum(run_dir, last))
    arrays = to_record(pack_update(*unpack_update(current), s.transfer_dtype), s.compress)
    for r in range(last + 1, s.rounds + 1):
        t0 = time.perf_counter()
        config = ConfigRecord({"run-dir": str(run_dir)})
        messages = strategy.configure_train(r, arrays, config, grid)
        replies = list(grid.send_and_receive(messages, timeout=s.round_timeout))
        agg, _ = strategy.aggregate_train(r, replies)
        st = strategy.last_round
        failed = {str(part[n]): _last_line(reason) for n, reason in st["failed"].items()}
        for n in set(st["bytes_down"]) - set(st["bytes_up"]) - set(st["failed"]):
            failed[str(part[n])] = f"no reply within {s.round_timeout:.0f} s"
        for k, reason in sorted(failed.items()):
            log.warning("round %d: client %s left out of the average: %s", r, k, reason)
        if agg is None or not st["bytes_up"]:
            reasons = "; ".join(f"{k}: {why}" for k, why in sorted(failed.items()))
            raise FederationFailed(
                f"round {r}: every drone failed, nothing to average ({reasons}); rounds up to "
                f"{history[-1]['round']} are kept, a rerun resumes there",
                run_dir,
            )
        entry = {
            "round": r,
            "bytes_down": {str(part[n]): b for n, b in st["bytes_down"].items()},
            "bytes_up": {str(part[n]): b for n, b in st["bytes_up"].items()},
            "failed": failed,
        }
        update = from_record(agg)
        history.append(evaluator.finish_round(run_dir, r, update, entry, t0))
        save_momentum(run_dir, r, strategy.server_state())
        save_rounds(run_dir, s, history)
        arrays = to_record(pack_update(*unpack_update(update), s.transfer_dtype), s.compress)
    evaluator.write_final(run_dir, history[-1]["round"])


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


def _last_line(reason: str) -> str:
    """The last non-empty line of an error report, without terminal colour codes."""
    lines = [ln.strip() for ln in re.sub(r"\x1b\[[0-9;]*m", "", reason).splitlines()]
    return ([ln for ln in lines if ln] or [""])[-1][:300]


def _message(grid: Grid, node: int, message_type: str, config: ConfigRecord) -> Message:
    return Message(RecordDict({"config": config}), dst_node_id=node, message_type=message_type)


def _discover(grid: Grid, s: FedSettings, run_dir: Path) -> dict[int, int]:
    """partition id -> node id of every drone (waits until all ``n_clients`` are connected)."""
    while len(node_ids := list(grid.get_node_ids())) < s.n_clients:
        time.sleep(1.0)
    config = ConfigRecord({"run-dir": str(run_dir)})
    msgs = [_message(grid, n, MessageType.QUERY, config) for n in node_ids]
    found: dict[int, int] = {}
    for reply in grid.send_and_receive(msgs, timeout=s.round_timeout):
        if reply.has_error():
            why = _last_line(reply.error.reason)
            raise FederationFailed(f"drone {reply.metadata.src_node_id} failed to start: {why}")
        found[int(reply.content["info"]["partition-id"])] = reply.metadata.src_node_id
    if sorted(found) != list(range(s.n_clients)):
        raise FederationFailed(f"expected partitions 0..{s.n_clients - 1}, found {sorted(found)}")
    return found


class GlobalEvaluator:
    """Holds a trainer for the global model: tests it, checkpoints it, writes the final one."""

    def __init__(self, s: FedSettings) -> None:
        from dronecap.nerf.trainer import Trainer

        self.s = s
        self.test = test_split(s.shards[0], s.eval_views)
        self.trainer = Trainer(s.train_config(), train_split(s.shards[0]))

    def finish_round(
        self, run_dir: Path, r: int, update: dict[str, np.ndarray], entry: dict, t0: float
    ) -> dict:
        """Install ``update`` as the global model, save it, test it; returns the round's entry.

        Without an exchanged grid the global model's grid is rebuilt from its own densities.
        """
        install_global(self.trainer, update, rebuild=True)
        with atomic_output(round_file(Path(run_dir) / "global", r)) as tmp:
            self.trainer.save(tmp)
        metrics = self.trainer.evaluate(self.test)
        if not (np.isfinite(metrics["psnr"]) and np.isfinite(metrics["ssim"])):
            raise FederationFailed(
                f"round {r}: the global model's test PSNR is {metrics['psnr']} (diverged); "
                "nothing recorded for this round",
                run_dir,
            )
        up = sum(entry["bytes_up"].values())
        down = sum(entry["bytes_down"].values())
        entry.update(
            psnr=float(metrics["psnr"]),
            ssim=float(metrics["ssim"]),
            steps=self.s.pretrain + r * self.s.local_steps,
            participants=len(entry["bytes_up"]),
            bytes_up_total=up,
            bytes_down_total=down,
            link_s=_round_link_time(entry),
            wall_s=time.perf_counter() - t0,
        )
        entry.setdefault("failed", {})
        log.info(
            "round %d: global PSNR %.2f dB (%d clients)", r, entry["psnr"], entry["participants"]
        )
        return entry

    def load_global(self, run_dir: Path, r: int) -> tuple[dict, dict | None]:
        """(model, grid or None) of the saved global model of round ``r``, for broadcasting."""
        from dronecap.nerf.trainer import Trainer

        t = Trainer.load(round_file(Path(run_dir) / "global", r))
        return t.model_weights(), (t.grid_state() if self.s.exchange_grid else None)

    def write_final(self, run_dir: Path, r: int) -> None:
        """Make ``run_dir`` a run folder of ``dronecap render``/``eval``: ``checkpoint.pt`` (the
        global model of round ``r``) and ``run.json`` (the coordinator's shard, which holds the
        common test set)."""
        src = round_file(Path(run_dir) / "global", r)
        with atomic_output(Path(run_dir) / FINAL) as tmp:
            tmp.write_bytes(src.read_bytes())
        info = {"dataset": self.s.shards[0], "config": self.trainer.cfg.__dict__, "round": r}
        with atomic_output(Path(run_dir) / "run.json") as tmp:
            tmp.write_text(json.dumps(info, indent=1, default=list))


def link_time(n_bytes: int) -> float | None:
    """Modelled seconds to send ``n_bytes`` over the drone radio (the GAP9 cost model's link);
    None while that model is not installed."""
    try:
        from dronecap.gap9.model import link_time_s
    except ImportError:
        return None
    return float(link_time_s(n_bytes))


def _round_link_time(entry: dict) -> float | None:
    """Modelled link seconds of a round: every upload and download in turn over the one shared
    radio channel (as the paper counts it: 4 x 0.52 MB each way -> 2.24 s at 15 Mbit/s)."""
    return link_time(sum(entry["bytes_up"].values()) + sum(entry["bytes_down"].values()))


# ----------------------------------------------------------------------------------------------
# rounds.json
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------
